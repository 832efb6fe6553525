"""Generated blocks inside hand-written pages: a command rewrites what lies between
``<!-- name -->`` and ``<!-- /name -->`` and leaves the prose around it alone (the README's results
table, the recipe page's ablation and robustness tables)."""

from __future__ import annotations

import re
from pathlib import Path


def replace_between(page: Path, marker: str, lines: list[str]) -> bool:
    """Put ``lines`` between the page's ``marker`` comments; False when the page or its markers are
    missing (an installed package has no README to update)."""
    page = Path(page)
    if not page.is_file():
        return False
    text = page.read_text()
    pattern = re.compile(rf"(<!-- {re.escape(marker)} -->\n).*?(<!-- /{re.escape(marker)} -->)", re.S)
    if not pattern.search(text):
        return False
    page.write_text(pattern.sub(lambda m: m.group(1) + "".join(line + "\n" for line in lines) + m.group(2), text))
    return True
