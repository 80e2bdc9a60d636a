"""Command line shared by the benchmark scripts that run on a TUM sequence."""

from __future__ import annotations

import argparse

from covo_gtsam.datasets.tum import TumSequence


def sequence_from_command_line(doc: str | None) -> tuple[TumSequence, int]:
    """Parse ``SEQUENCE [--max-frames N]``; return the sequence and the number of frames to use."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", help="TUM RGB-D sequence folder (rgb.txt, depth.txt, groundtruth.txt)")
    ap.add_argument("--max-frames", type=int, default=None, help="use only the first N frames")
    args = ap.parse_args()
    seq = TumSequence(args.sequence)
    return seq, len(seq) if args.max_frames is None else min(args.max_frames, len(seq))
