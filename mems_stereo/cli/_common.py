"""Shared helpers of the CLI commands: output verbosity and progress bars."""

from __future__ import annotations


class Reporter:
    """Prints according to ``--quiet`` / ``--verbose``; progress on stderr."""

    def __init__(self, args):
        self.quiet = bool(getattr(args, "quiet", False))
        self.verbose = bool(getattr(args, "verbose", False))

    def info(self, msg: str = "") -> None:
        if not self.quiet:
            print(msg)

    def detail(self, msg: str) -> None:
        if self.verbose and not self.quiet:
            print(msg)

    def progress(self, total: int, desc: str, unit: str = "shot"):
        """A tqdm progress bar on stderr (disabled when quiet or not a terminal)."""
        from mems_stereo.cli._ux import progress_bar

        return progress_bar(total, desc, unit, quiet=self.quiet)
