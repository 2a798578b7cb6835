"""Command-line arguments the MRCLAM-6 benches share: which robots, where the data
is, where the results go, how many replays run in parallel."""

from __future__ import annotations

import argparse
from pathlib import Path

from service.offline.datasets.mrclam import default_mrclam_dir


def mrclam_parser(description: str | None) -> argparse.ArgumentParser:
    """A parser with --robots, --data, --out and --jobs (2); add a bench's own."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--robots", default="1,2,3,4,5")
    parser.add_argument("--data", type=Path, default=default_mrclam_dir())
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--jobs", type=int, default=2)
    return parser


def parse_mrclam(parser: argparse.ArgumentParser) -> tuple[argparse.Namespace, list[int]]:
    """The arguments and the robots; exits with a clear message without the data."""
    args = parser.parse_args()
    if not args.data.is_dir():
        raise SystemExit(f"MRCLAM data not found at {args.data} (set COVSLAM_DATA)")
    return args, [int(r) for r in args.robots.split(",")]
