"""report.json and report.md: the same results, one for programs and one for people.

The Markdown is rendered from the JSON document, not from the outcomes, so the two can never
disagree. Every figure appears beside its target with met / not met and its method; a section
that failed, was skipped or does not exist yet says so instead of silently missing.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import platform
import subprocess
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

from benchmarks.harness import Figure, Outcome

__all__ = ["collect_meta", "render_markdown", "to_document", "write_reports"]

_PACKAGES = ("biris-hw", "numpy", "python-periphery")
"""Distributions whose versions change the numbers, so the report records them."""

Document = dict[str, Any]


def collect_meta(
    *,
    seconds: float,
    quick: bool,
    only: Sequence[str] | None,
    load_errors: Mapping[str, str],
) -> dict[str, Any]:
    """Where and when the figures were taken: without this a number cannot be compared."""
    try:
        usable: int | None = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        usable = None
    commit, dirty = _git_state()
    return {
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "cpus_usable": usable,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "git_commit": commit,
        "git_dirty": dirty,
        "seconds": round(seconds, 3),
        "quick": quick,
        "only": list(only) if only is not None else None,
        "packages": {name: _version(name) for name in _PACKAGES},
        "load_errors": dict(load_errors),
    }


def to_document(meta: Mapping[str, Any], outcomes: Sequence[Outcome]) -> Document:
    """The report.json document: ``meta`` first, then one entry per section in suite order."""
    doc: Document = {"meta": dict(meta)}
    met = not_met = unjudged = 0
    for outcome in outcomes:
        entry: dict[str, Any] = {"status": outcome.status}
        if outcome.status in ("ok", "failed", "skipped"):
            entry["seconds"] = round(outcome.seconds, 3)
        if outcome.reason:
            entry["reason"] = outcome.reason
        if outcome.status == "failed":
            entry["error"] = outcome.error
            entry["traceback"] = outcome.traceback
        if outcome.status == "ok":
            entry["figures"] = {fig.name: _figure(fig) for fig in outcome.figures}
            for fig in outcome.figures:
                if fig.met is None:
                    unjudged += 1
                elif fig.met:
                    met += 1
                else:
                    not_met += 1
        doc[outcome.section] = entry
    doc["meta"]["summary"] = {"met": met, "not_met": not_met, "no_target": unjudged}
    return doc


def _figure(fig: Figure) -> dict[str, Any]:
    target = None
    if fig.target is not None:
        target = {
            "op": fig.target.op,
            "value": fig.target.value,
            "on": fig.target.on,
            "text": str(fig.target),
        }
    entry: dict[str, Any] = {
        "key": fig.key,
        "values": {name: _finite(v) for name, v in fig.values.items()},
        "unit": fig.unit,
        "target": target,
        "met": fig.met,
        "method": fig.method,
    }
    if fig.note:
        entry["note"] = fig.note
    return entry


def _finite(value: float) -> float | None:
    """JSON has no NaN or infinity; a value that is neither is written as null."""
    return float(value) if math.isfinite(value) else None


# -- Markdown ------------------------------------------------------------------------------------


def render_markdown(doc: Document) -> str:
    """A table per section: figure, value, target, met / not met, method."""
    meta = doc["meta"]
    summary = meta["summary"]
    commit = meta["git_commit"] or "unknown"
    if meta["git_dirty"]:
        commit += " (with uncommitted changes)"
    lines = [
        "# biris-hw benchmark report",
        "",
        f"- date: {meta['date']}; took {meta['seconds']:.1f} s"
        + ("; **quick run** (fewer repetitions, not for comparison)" if meta["quick"] else ""),
        f"- python: {meta['python']} on {meta['platform']}",
        f"- cpus: {meta['cpu_count']} ({meta['cpus_usable']} usable); commit: {commit}",
        "- packages: " + ", ".join(f"{k} {v or 'absent'}" for k, v in meta["packages"].items()),
        f"- targets: {summary['met']} met, {summary['not_met']} not met, "
        f"{summary['no_target']} without a target",
        "",
        "Values are medians over repeated rounds unless named otherwise (pNN = percentile, "
        "n = samples); the figure's target judges the value shown in bold.",
    ]
    for module, error in meta["load_errors"].items():
        lines += ["", f"**Benchmark module {module} could not be loaded:** {_cell(error)}"]
    for section, entry in doc.items():
        if section == "meta":
            continue
        lines += ["", f"## {section}", ""]
        lines += _section_lines(entry)
    return "\n".join(lines) + "\n"


def _section_lines(entry: Mapping[str, Any]) -> list[str]:
    status = entry["status"]
    if status == "not implemented":
        return ["Not implemented yet."]
    if status == "not run":
        return [f"Not run ({entry.get('reason', '')})."]
    if status == "skipped":
        return [f"Skipped: {_cell(entry['reason'])}"]
    if status == "failed":
        return [f"**Failed** after {entry['seconds']:.1f} s: `{_cell(entry['error'])}`"]
    figures: Mapping[str, Any] = entry["figures"]
    if not figures:
        return [f"Ran in {entry['seconds']:.1f} s but produced no figures."]
    rows = [f"Ran in {entry['seconds']:.1f} s.", ""]
    notes = [fig["note"] for fig in figures.values() if fig.get("note")]
    if notes:
        rows += [*(f"- {_cell(note)}" for note in notes), ""]
    rows += [
        "| figure | value | target | met | method |",
        "|---|---|---|---|---|",
    ]
    for name, fig in figures.items():
        target = fig["target"]
        judged = target["on"] if target else None
        value = "; ".join(
            f"**{k} {_number(v)}**" if k == judged else f"{k} {_number(v)}"
            for k, v in fig["values"].items()
        )
        met = {True: "met", False: "**not met**", None: "n/a"}[fig["met"]]
        rows.append(
            f"| {_cell(name)} ({_cell(fig['unit'])}) | {value} | "
            f"{_cell(target['text']) if target else 'none'} | {met} | {_cell(fig['method'])} |"
        )
    return rows


def _number(value: float | None) -> str:
    """Readable at a glance: grouped digits for rates, three significant figures otherwise."""
    if value is None:
        return "n/a"
    if value == int(value) and abs(value) < 1e15:
        return f"{int(value):,}"
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    return f"{value:.3g}"


def _cell(text: str) -> str:
    """A table cell stays one cell: no pipes, no line breaks."""
    return " ".join(str(text).split()).replace("|", "\\|")


# -- files ---------------------------------------------------------------------------------------


def write_reports(out: Path, meta: Mapping[str, Any], outcomes: Sequence[Outcome]) -> list[Path]:
    """Write report.json and report.md under ``out``; each replaces the old one whole."""
    doc = to_document(meta, outcomes)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / "report.json"
    md_path = out / "report.md"
    _replace(json_path, json.dumps(doc, indent=2, allow_nan=False) + "\n")
    _replace(md_path, render_markdown(doc))
    return [json_path, md_path]


def _replace(path: Path, text: str) -> None:
    """Write beside and rename, so a reader never sees half a report."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def _version(dist: str) -> str | None:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _git_state() -> tuple[str | None, bool | None]:
    """The checkout's commit and whether it has local changes; ``None`` outside a checkout."""
    here = Path(__file__).resolve().parent
    # Optional locks off: engineers share this checkout, and a report must never take the index.
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0"}
    try:
        head = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            env=env,
            check=True,
        ).stdout.strip()
        diff = subprocess.run(
            ["git", "-C", str(here), "diff", "--quiet", "HEAD", "--"],
            capture_output=True,
            timeout=10,
            env=env,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None, None
    dirty = {0: False, 1: True}.get(diff.returncode)
    return head or None, dirty
