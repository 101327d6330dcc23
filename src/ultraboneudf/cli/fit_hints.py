"""A reconstruction's fit issues (:class:`~ultraboneudf.pipeline.FitIssue`) as the command line
says them: the advice spelled as its own flags (``--seed``, ``--set extract.trim_mm=3``)."""

from __future__ import annotations

import sys
from typing import Any, TextIO


def cli_text(issue: Any) -> str:
    """``issue`` described, with the flags that address it."""
    return issue.text(lambda name: f"--{name}", lambda key, value: f"--set {key}={value:g}")


def print_fit_issues(rec: Any, prefix: str, file: TextIO | None = None) -> None:
    """One ``PREFIX: warning: …`` line per fit issue of ``rec`` (shown even with ``--quiet``: they
    concern the result)."""
    for issue in rec.fit_issues():
        print(f"{prefix}: warning: {cli_text(issue)}", file=file or sys.stderr)
