"""MkDocs hook: the configuration page's default column, read from the config schema
(the one place every default is written)."""

from __future__ import annotations

import json
import re

from parammap.config import default

ROW = re.compile(r"^\| (`[^|]*`) \| (.*) \|$")


def _default(cell: str) -> str:
    keys = re.findall(r"`([^`]+)`", cell)
    prefix = keys[0].rsplit(".", 1)[0] if keys and "." in keys[0] else ""
    values = []
    for i, key in enumerate(keys):
        full = key if i == 0 or "." in key else f"{prefix}.{key}"
        try:
            values.append(json.dumps(default(full)).replace('"', "`"))
        except KeyError:
            return ""
    return ", ".join(values)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri != "configuration.md":
        return markdown
    out = []
    for line in markdown.split("\n"):
        if line == "| key | meaning |":
            line = "| key | default | meaning |"
        elif line == "|---|---|":
            line = "|---|---|---|"
        elif m := ROW.match(line):
            line = f"| {m.group(1)} | {_default(m.group(1))} | {m.group(2)} |"
        out.append(line)
    return "\n".join(out)
