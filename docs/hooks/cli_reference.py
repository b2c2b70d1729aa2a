"""The command-line reference (`docs/cli.md`) from the `rbdyn` command's own parser.

`docs/cli.md` holds a marker `<!-- rbdyn-help -->` for the command itself and one
`<!-- rbdyn-help SUBCOMMAND -->` per subcommand. Each is replaced by the usage line and a
table of the arguments, their defaults and their help, read from the parser that
`rbdyn_jax.cli` builds, so the page shows what the command accepts. A subcommand with no
marker in the page, or a marker naming no subcommand, is a warning (an error under
`mkdocs build --strict`): a new subcommand cannot go undocumented.

The parser is `rbdyn_jax.cli.build_parser()`, the one `rbdyn` itself parses with.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
from collections.abc import Iterator

log = logging.getLogger("mkdocs.hooks.cli_reference")

PAGE = "cli.md"
MARKER = re.compile(r"^<!-- rbdyn-help(?: (?P<cmd>[\w-]+))? -->[ \t]*$", re.M)
WIDTH = "88"  # columns of the usage lines


def cli_parser() -> argparse.ArgumentParser:
    """The `rbdyn` command's argument parser."""
    from rbdyn_jax import cli

    return cli.build_parser()


def subcommands(parser: argparse.ArgumentParser) -> dict[str, tuple[argparse.ArgumentParser, str]]:
    """Subcommand name → (its parser, its one-line help), in the parser's order."""
    out = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            for name, sub in action.choices.items():
                out[name] = (sub, helps.get(name, ""))
    return out


@contextlib.contextmanager
def _columns() -> Iterator[None]:
    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = WIDTH
    try:
        yield
    finally:
        if old is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = old


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", r"\|")


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
        return ""
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        return "off" if isinstance(action, argparse._StoreTrueAction) else "on"
    if action.default is None or action.default == argparse.SUPPRESS:
        return "—"
    return f"`{action.default}`"


def _name(action: argparse.Action, formatter: argparse.HelpFormatter) -> str:
    if not action.option_strings:
        return f"`{action.metavar or action.dest}`"
    if action.nargs == 0:
        return ", ".join(f"`{s}`" for s in action.option_strings)
    metavar = formatter._format_args(action, action.dest.upper())
    return ", ".join(f"`{s} {metavar}`" for s in action.option_strings)


def render(parser: argparse.ArgumentParser, prog: str | None = None) -> str:
    """Markdown: the usage line of `parser` and a table of its arguments."""
    with _columns():
        usage = parser.format_usage().strip()
        formatter = parser._get_formatter()
    rows = []
    for action in parser._actions:
        if isinstance(action, (argparse._SubParsersAction, argparse._HelpAction)):
            continue  # the subcommands have their own sections; every command takes -h
        help_text = action.help if action.help != argparse.SUPPRESS else ""
        if help_text and "%(" in help_text:
            help_text = help_text % {**vars(action), "prog": parser.prog}
        rows.append(f"| {_name(action, formatter)} | {_default(action)} | {_cell(help_text)} |")
    table = "\n".join(["| argument | default | meaning |", "|---|---|---|", *rows])
    return f"```text\n{usage}\n```\n\n{table}\n"


def _overview(parser: argparse.ArgumentParser) -> str:
    rows = [
        f"| [`{name}`](#rbdyn-{name}) | {_cell(help_text)} |"
        for name, (_, help_text) in subcommands(parser).items()
    ]
    table = "\n".join(["| subcommand | what it does |", "|---|---|", *rows])
    return f"{render(parser)}\n{table}\n"


def on_page_markdown(markdown: str, page, **kwargs) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    parser = cli_parser()
    commands = subcommands(parser)
    seen: set[str] = set()

    def replace(m: re.Match) -> str:
        cmd = m["cmd"]
        if cmd is None:
            return _overview(parser)
        if cmd not in commands:
            log.warning(
                f"{PAGE}: marker for `rbdyn {cmd}`, which is not a subcommand "
                f"(subcommands: {', '.join(commands)})"
            )
            return m[0]
        seen.add(cmd)
        return render(commands[cmd][0])

    markdown = MARKER.sub(replace, markdown)
    for cmd in commands:
        if cmd not in seen:
            log.warning(
                f"{PAGE}: `rbdyn {cmd}` is not documented: add a section with the "
                f"marker <!-- rbdyn-help {cmd} -->"
            )
    return markdown
