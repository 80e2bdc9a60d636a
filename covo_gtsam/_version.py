"""The package's version: the one place it is written (``pyproject.toml`` reads it from here).

Reading it from the installed metadata (``importlib.metadata``) cost every ``covo`` command about
35 ms of start-up for the modules that load.
"""

__version__ = "0.1.0"
