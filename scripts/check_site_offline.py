"""Check that a built documentation site loads nothing from the internet.

Usage: ``python scripts/check_site_offline.py [SITE_DIR]`` (default ``site``). Fails (exit 1)
listing every page or stylesheet that would fetch a remote resource: a ``<script src>``,
``<img src>``, ``<iframe src>``, ``<link href>`` that is loaded (stylesheet, preload,
preconnect, icon, manifest), a CSS ``@import`` or ``url(...)``, or a web-font host anywhere.
Plain hyperlinks (``<a href="https://...">``) are allowed: following one is the reader's
choice. Pages are parsed with the standard library's HTML parser.
"""

from __future__ import annotations

import re
import sys
from html.parser import HTMLParser
from pathlib import Path

REMOTE = re.compile(r"^\s*(https?:)?//", re.IGNORECASE)
LOADED_LINKS = {
    "stylesheet",
    "preload",
    "preconnect",
    "dns-prefetch",
    "icon",
    "manifest",
    "modulepreload",
    "prefetch",
}
FONT_HOSTS = re.compile(r"fonts\.(googleapis|gstatic)\.com|use\.typekit|fonts\.bunny")
CSS_URL = re.compile(r"(@import\s+(url\()?|url\()\s*['\"]?\s*((https?:)?//[^'\")\s]+)", re.I)


class _Resources(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.remote: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = {k: v or "" for k, v in attrs}
        if tag in ("script", "img", "iframe", "source", "audio", "video") and REMOTE.match(
            a.get("src", "")
        ):
            self.remote.append(f"<{tag} src={a['src']}>")
        if tag == "link" and REMOTE.match(a.get("href", "")):
            rels = set(a.get("rel", "").lower().split())
            if rels & LOADED_LINKS:
                self.remote.append(f"<link rel={a['rel']} href={a['href']}>")


def problems(site: Path) -> list[str]:
    """Every remote resource the site would load, as ``file: what``."""
    out = []
    for path in sorted(site.rglob("*")):
        if path.suffix not in (".html", ".css", ".js") or not path.is_file():
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        name = path.relative_to(site)
        if path.suffix == ".html":
            parser = _Resources()
            parser.feed(text)
            out += [f"{name}: {r}" for r in parser.remote]
        if path.suffix == ".css":
            out += [f"{name}: css {m.group(3)}" for m in CSS_URL.finditer(text)]
        out += [f"{name}: web font host {m.group(0)}" for m in FONT_HOSTS.finditer(text)]
    return out


def main(argv: list[str]) -> int:
    """Print the problems of the site in ``argv[0]`` (default ``site``); 1 if any."""
    site = Path(argv[0] if argv else "site")
    if not (site / "index.html").is_file():
        print(f"{site}/index.html not found: build the site first (mkdocs build)")
        return 1
    found = problems(site)
    for p in found:
        print(p)
    n_pages = sum(1 for _ in site.rglob("*.html"))
    print(f"{n_pages} pages checked: {len(found)} remote resources")
    return 1 if found else 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
