"""The dashboard's HTML shell: ``templates/index.html`` with the job options form filled in from the API's own
option list (``service.jobs.options.CLIENT_OPTIONS``), so the form offers exactly what an upload accepts."""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from html import escape
from pathlib import Path

from pipeline.job.options import JobOptions
from service.jobs.options import (
    CLIENT_OPTIONS,
    known_colour_spaces,
    known_modes,
    known_presets,
    known_restore_formats,
)

WEB_DIR = Path(__file__).resolve().parent
STATIC_DIR = WEB_DIR / "static"
TEMPLATE = WEB_DIR / "templates" / "index.html"
OPTIONS_MARK = "<!--options-->"

_CHOICES = {"preset": known_presets, "mode": known_modes, "colour_space": known_colour_spaces,
            "restore_format": known_restore_formats}


def _field_html(name: str, default: object, help_text: str, bounds: dict) -> str:
    label = f'<span>{escape(name)}</span>'
    title = escape(help_text, quote=True)
    if name in _CHOICES:
        opts = "".join(f'<option value="{escape(c)}"{" selected" if c == default else ""}>{escape(c)}</option>'
                       for c in _CHOICES[name]())
        return f'<label title="{title}">{label}<select name="{escape(name)}">{opts}</select></label>'
    attrs = [f'name="{escape(name)}"', 'type="number"', 'inputmode="decimal"',
             'step="1"' if name in ("iterations", "max_width", "seed") else 'step="any"']
    for key, html_attr in (("ge", "min"), ("gt", "min"), ("le", "max")):
        if key in bounds:
            attrs.append(f'{html_attr}="{bounds[key]}"')
    placeholder = "default" if default is None else str(default)
    attrs.append(f'placeholder="{escape(placeholder, quote=True)}"')
    return f'<label title="{title}">{label}<input {" ".join(attrs)}></label>'


def options_form() -> str:
    """One ``<label>`` per client option: a select for the named choices, a number field (empty = the default)
    for the rest; the option's help text is the tooltip."""
    spec = {f.name: f for f in dataclasses.fields(JobOptions)}
    return "\n".join(_field_html(name, spec[name].default, spec[name].metadata.get("help", ""), bounds)
                     for name, bounds in CLIENT_OPTIONS.items())


@lru_cache(maxsize=1)
def render_index() -> str:
    """The page (the same for every visitor and every client-side route; no key is involved in serving it)."""
    return TEMPLATE.read_text(encoding="utf-8").replace(OPTIONS_MARK, options_form())
