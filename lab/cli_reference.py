"""The `dcdi` command reference (docs/cli.md), generated from the parser.

    python -m lab cli-reference > docs/cli.md
    python -m lab cli-reference --write      # the same, into docs/cli.md

A test compares docs/cli.md with this text, so the page changes with the
options. The text does not depend on the terminal's width.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

DOC = Path(__file__).resolve().parents[1] / "docs" / "cli.md"

INTRO = """# The `dcdi` command

Generated from the command's parser by `python -m lab cli-reference --write`;
do not edit by hand. `dcdi COMMAND --help` prints the same.

{units}

Every error a user can cause ends in one line on standard error,
`dcdi: error: ...`, naming the file or option and what is allowed, with exit
status 2.
"""


def _subcommands(parser) -> list[tuple[str, str | None, argparse.ArgumentParser]]:
    """(name, help or None when hidden, parser) of ``parser``'s subcommands, in order."""
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            helps = {c.dest: c.help for c in a._choices_actions}
            return [(name, helps.get(name), p) for name, p in a.choices.items()]
    return []


def _expand(action, prog: str) -> str:
    return argparse.HelpFormatter(prog)._expand_help(action) if action.help else ""


def _invocation(action) -> str:
    if not action.option_strings:
        name = action.metavar or (("{" + ",".join(map(str, action.choices)) + "}") if action.choices else action.dest)
        return {"*": f"[{name} ...]", "+": f"{name} [{name} ...]", "?": f"[{name}]"}.get(action.nargs, name)
    opts = ", ".join(action.option_strings)
    if action.nargs == 0:
        return opts
    meta = action.metavar or (("{" + ",".join(map(str, action.choices)) + "}") if action.choices
                              else action.dest.upper())
    if isinstance(meta, tuple):
        return f"{opts} {' '.join(meta)}"
    if action.nargs == "+":
        return f"{opts} {meta} [{meta} ...]"
    if isinstance(action.nargs, int):
        return f"{opts} {' '.join([meta] * action.nargs)}"
    return f"{opts} {meta}"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _options(parser, prog: str) -> list[str]:
    rows = []
    for group in parser._mutually_exclusive_groups:
        names = " / ".join(a.option_strings[0] for a in group._group_actions)
        rows.append(f"One of {names}{' (required)' if group.required else ''}.")
    out = []
    for a in parser._actions:
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)) or a.help == argparse.SUPPRESS:
            continue
        needed = " (required)" if a.required and a.option_strings else ""
        out.append(f"| `{_invocation(a)}` | {_cell(_expand(a, prog))}{needed} |")
    if not out:
        return rows
    return rows + ([""] if rows else []) + ["| argument | meaning |", "|---|---|"] + out


def _description(parser, help_: str | None) -> str:
    """The command's description without the units (the page states them once)."""
    from dcdi_core.cli.common import UNITS
    text = (parser.description or help_ or "").replace(UNITS, "")
    return " ".join(text.split())


def _section(name: str, parser, help_: str | None, depth: int) -> list[str]:
    prog = parser.prog
    lines = [f"{'#' * min(depth, 6)} `{prog}`", ""]
    text = _description(parser, help_)
    if text:
        lines += [text, ""]
    subs = _subcommands(parser)
    if subs:
        lines += [f"- `{p.prog}`: {' '.join(h.split())}" for n, h, p in subs if h is not None] + [""]
    opts = _options(parser, prog)
    if opts:
        lines += opts + [""]
    for n, h, p in subs:
        if h is not None:
            lines += _section(n, p, h, depth + 1)
    return lines


def reference(parser=None) -> str:
    """The markdown reference of every command: its help and options."""
    from dcdi_core.cli import build_parser
    from dcdi_core.cli.common import UNITS
    parser = parser or build_parser()
    lines = [INTRO.format(units=UNITS[0].upper() + UNITS[1:])]
    lines += ["## Commands", ""]
    lines += [f"- `dcdi {n}`: {' '.join(h.split())}" for n, h, _ in _subcommands(parser) if h is not None] + [""]
    for n, h, p in _subcommands(parser):
        if h is not None:
            lines += _section(n, p, h, 2)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab cli-reference", description=__doc__.split("\n\n")[0])
    p.add_argument("--write", action="store_true", help=f"write {DOC} (atomically) instead of printing")
    args = p.parse_args(argv)
    text = reference()
    if args.write:
        from dcdi_core.atomic import write_text
        write_text(DOC, text)
        print(f"wrote {DOC}")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
