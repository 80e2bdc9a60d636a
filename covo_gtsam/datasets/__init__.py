"""Dataset readers, one module per format."""


def frame_count(seq, max_frames: int | None) -> int:
    """How many of ``seq``'s frames a run takes: all of them, or the first ``max_frames``."""
    return len(seq) if max_frames is None else min(len(seq), max_frames)
