"""Subcommands of the pipeline package (run, demo, config); filled in by the pipelines issue."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the pipeline's subcommands."""
