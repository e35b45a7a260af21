"""Fill every figure block and inline value of the README and docs/ from docs/figures/*.json.

    python scripts/render_docs.py            # rewrite the pages whose figures changed
    python scripts/render_docs.py --check    # exit 1 and name the pages that would change

The block syntax is in ``scripts/figures.py``; ``tests/test_figures.py`` runs the check.
"""

from __future__ import annotations

import sys

import figures


def stale_pages() -> tuple[list[tuple], list[str]]:
    """``(pages whose figures changed with their new text, a line per page that cannot be
    rendered because a benchmark's JSON is missing)``."""
    out, missing = [], []
    for page in figures.PAGES:
        text = page.read_text()
        try:
            new = figures.render_page(text)
        except FileNotFoundError as exc:
            missing.append(f"{page.relative_to(figures.ROOT)}: {exc}")
            continue
        if new != text:
            out.append((page, new))
    return out, missing


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    stale, missing = stale_pages()
    for page, new in stale:
        rel = page.relative_to(figures.ROOT)
        if "--check" in argv:
            print(f"{rel}: its figures differ from docs/figures/ (python scripts/render_docs.py)")
        else:
            page.write_text(new)
            print(f"rendered {rel}")
    for line in missing:
        print(line, file=sys.stderr)
    return 1 if missing or (stale and "--check" in argv) else 0


if __name__ == "__main__":
    sys.exit(main())
