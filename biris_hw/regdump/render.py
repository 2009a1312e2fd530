"""A dump for people (an aligned table) and for scripts (one JSON object with stable keys)."""

from __future__ import annotations

from biris_hw.regdump.model import Dump, Json, hex_offset

__all__ = ["format_table", "to_json"]


def format_table(dump: Dump, changed: frozenset[tuple[str, str]] = frozenset()) -> str:
    """The dump as aligned text, one section per heading; changed rows start with ``*``."""
    all_rows = [r for s in dump.sections for r in s.rows]
    w_name = max(len("name"), *(len(r.name) for r in all_rows))
    w_off = max(
        len("offset"), *(len(hex_offset(r.offset)) for r in all_rows if r.offset is not None)
    )
    w_raw = max(len("raw"), *(len(r.raw_text) for r in all_rows))
    lines = [f"source: {dump.source}" if dump.source else "source: (unnamed)"]
    for section in dump.sections:
        lines += ["", f"{section.title}  [{section.where}; at 0x{section.base:04X} of the source]"]
        lines.append(f"  {'name':<{w_name}}  {'offset':<{w_off}}  {'raw':<{w_raw}}  decoded")
        for row in section.rows:
            mark = "*" if (section.key, row.name) in changed else " "
            off = "" if row.offset is None else hex_offset(row.offset)
            decoded = "" if row.decoded == row.raw_text else row.decoded  # plain hex: say it once
            line = f"{mark} {row.name:<{w_name}}  {off:<{w_off}}  {row.raw_text:<{w_raw}}  "
            lines.append((line + decoded).rstrip())
    return "\n".join(lines) + "\n"


def to_json(dump: Dump, changed: frozenset[tuple[str, str]] = frozenset()) -> dict[str, Json]:
    """The dump as one JSON-ready object with stable keys.

    Each section holds ``title``, ``base``, ``registers`` (by name: offset, width, access, raw,
    value, decoded; raw and value are null when not read) and its derived values by name.
    ``changed`` lists ``"section.row"`` for rows that differ from the previous dump.
    """
    out: dict[str, Json] = {"source": dump.source, "layout": dict(dump.layout)}
    for section in dump.sections:
        body: dict[str, Json] = {"title": section.title, "base": section.base, "registers": {}}
        for row in section.rows:
            if row.register:
                body["registers"][row.name] = {
                    "offset": row.offset,
                    "width": row.width,
                    "access": row.access,
                    "raw": row.raw,
                    "value": row.value,
                    "decoded": row.decoded,
                }
            else:
                body[row.name] = row.value
        out[section.key] = body
    out["changed"] = sorted(f"{key}.{name}" for key, name in changed)
    return out
