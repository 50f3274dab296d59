"""The QA report's audit section, filled in when the report is published (``report.publish``):
the trail's state belongs to that moment, not to the stage that drew the report. Kept apart from
the report's drawing code so that publishing does not run (nor hash into its stage key) that code."""

from __future__ import annotations

import html
from typing import Any

__all__ = ["AUDIT_MARK", "UNVERIFIED", "fill_audit", "strip_audit"]

AUDIT_MARK = "<!-- weldrecon: audit status -->"
UNVERIFIED = {"intact": False, "entries": 0, "head_seq": None, "head_hash": None,
              "problems": ["the trail was not verified for this publication"]}


def fill_audit(page: str, status: dict[str, Any]) -> str:
    """The report with the audit trail's verification (``status``: ``intact``, ``entries``,
    ``head_seq``, ``head_hash``, ``problems``) in its marked place."""
    if AUDIT_MARK not in page:
        raise ValueError("the QA report has no place for the audit status (not made by this version?)")
    problems = status.get("problems") or []
    verdict = ("intact: every entry chains to the one before it and matches its hash" if status["intact"]
               else f"NOT intact: {len(problems)} problem(s)")
    items = "".join(f"<li>{html.escape(p)}</li>" for p in problems)
    block = (f'<p class="{"ok" if status["intact"] else "bad"}">Audit trail {html.escape(verdict)}, '
             f'verified when this report was published: {status["entries"]} entries, the last before this '
             f'publication seq {status["head_seq"]}, sha256 <code>{html.escape(str(status["head_hash"]))}</code>. '
             'The run-finished entry that follows it records this file\'s sha256; check the folder later with '
             '<code>weldrecon audit verify RUN_DIR --head HASH</code>.</p>' + (f"<ul>{items}</ul>" if items else ""))
    return page.replace(AUDIT_MARK, _BEGIN + block + _END, 1)


_BEGIN, _END = "<!-- weldrecon: audit status begin -->", "<!-- weldrecon: audit status end -->"


def strip_audit(page: str) -> str:
    """A published report as its stage drew it: the audit section back to its mark (what two runs
    of the same inputs must agree on byte for byte; the audit section is each run folder's own)."""
    start, end = page.find(_BEGIN), page.find(_END)
    if start < 0 or end < start:
        raise ValueError("the QA report has no filled audit section")
    return page[:start] + AUDIT_MARK + page[end + len(_END):]
