"""The operator dashboard: server-rendered pages (Jinja2), plain JS modules, no CDN."""

from pathlib import Path

#: Static assets, mounted at ``/static`` by :func:`app.main.create_app`.
STATIC_DIR = Path(__file__).resolve().parent / "static"
#: Jinja2 templates of the pages.
TEMPLATES_DIR = Path(__file__).resolve().parent / "templates"
