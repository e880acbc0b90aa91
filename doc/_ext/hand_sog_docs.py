"""Directives of this documentation: the parameter table from ``ros/params.py`` and the ``--help`` of a command.

One source for the table: :data:`hand_sog_tracker.ros.params.PARAM_SPECS` (the node declares
exactly these, and ``config/hand_sog_tracker.yaml`` is generated from them too).
"""

from __future__ import annotations

from docutils import nodes
from docutils.parsers.rst import Directive


def _cell(text: str, literal: bool = False) -> nodes.entry:
    para = nodes.paragraph()
    para += nodes.literal(text=text) if literal else nodes.Text(text)
    entry = nodes.entry()
    entry += para
    return entry


def _default(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


class ParameterTable(Directive):
    """A table of every node parameter: name, type, default, range or choices, description."""

    has_content = False

    def run(self) -> list[nodes.Node]:
        from hand_sog_tracker.ros.params import PARAM_SPECS

        header = ("name", "type", "default", "range", "description")
        widths = (18, 6, 10, 14, 52)
        table = nodes.table(classes=["hand-sog-parameters"])
        group = nodes.tgroup(cols=len(header))
        table += group
        for w in widths:
            group += nodes.colspec(colwidth=w)
        head = nodes.thead()
        row = nodes.row()
        for h in header:
            row += _cell(h)
        head += row
        group += head
        body = nodes.tbody()
        for s in PARAM_SPECS:
            row = nodes.row()
            if s.choices:
                rng = ", ".join(s.choices)
            elif s.low is not None:
                rng = f"{s.low} .. {s.high}"
            else:
                rng = ""
            if s.read_only:
                rng = f"{rng}; read-only" if rng else "read-only"
            for text, literal in ((s.name, True), (type(s.default).__name__, False), (_default(s.default), True),
                                  (rng, False), (s.description, False)):
                row += _cell(text, literal)
            body += row
        group += body
        return [table]


def setup(app) -> dict:
    app.add_directive("hand-sog-parameters", ParameterTable)
    app.add_directive("hand-sog-help", CommandHelp)
    return {"parallel_read_safe": True, "parallel_write_safe": True}


class CommandHelp(Directive):
    """``--help`` of a command whose parser is built inside its ``main`` (no ``build_parser``):
    the module is run with ``--help`` at build time and its output shown."""

    required_arguments = 1  # the module, e.g. hand_sog_tracker.tools.benchmark

    def run(self) -> list[nodes.Node]:
        import subprocess
        import sys

        module = self.arguments[0]
        out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True,
                             timeout=120, env={"COLUMNS": "100", "PATH": "/usr/bin:/bin"})
        if out.returncode != 0:
            raise self.error(f"{module} --help failed: {out.stderr.strip()[-300:]}")
        return [nodes.literal_block(text=out.stdout, language="text")]
