"""Write ``docs/cli.md``, every command's options, from the command-line parsers themselves.

    python scripts/cli_doc.py [--check]

The page is made from :func:`blurcalib.cli.build_parser`, the parsers of ``blurcalib experiment
NAME`` (``blurcalib.paper.*.build_parser``) and ``app.py``'s parser: one section per command, its
description, a usage line and one line per option with its help text (defaults expanded). So the
page says what ``--help`` says. ``--check`` writes nothing and exits with 1 when ``docs/cli.md``
differs from what the parsers make (``tests/scripts/test_cli_doc.py`` runs the same comparison).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "cli.md"
COMMANDS = ("calibrate", "extract", "demo", "pattern", "synth", "experiment")
"""The subcommands in the page's order (``view`` is the app's section)."""
EXPERIMENTS = ("patterns", "alignment", "psf-quality", "threshold-sweep", "generic")


def _metavar(action: argparse.Action) -> str:
    """The value an option takes, as ``--help`` spells it (``{a,b}`` for choices)."""
    if action.metavar is not None:
        return str(action.metavar)
    if action.choices is not None:
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    return action.dest.upper() if action.option_strings else action.dest


def _invocation(action: argparse.Action) -> str:
    """``--name VALUE`` of an option (``VALUE ...`` for several values), or a positional's name."""
    value = _metavar(action)
    if action.nargs in ("+", "*"):
        value = f"{value} ..."
    elif action.nargs == "?":
        value = f"[{value}]"
    if not action.option_strings:
        return value
    names = ", ".join(action.option_strings)
    return names if action.nargs == 0 else f"{names} {value}"


def _help(action: argparse.Action, prog: str) -> str:
    """An action's help text with its ``%(...)s`` fields filled as argparse fills them."""
    params = {k: v for k, v in vars(action).items() if v is not argparse.SUPPRESS}
    params = {k: getattr(v, "__name__", v) for k, v in params.items()}
    if params.get("choices") is not None:
        params["choices"] = ", ".join(str(c) for c in params["choices"])
    params["prog"] = prog
    return " ".join(((action.help or "") % params).split())


def _usage(parser: argparse.ArgumentParser, prog: str) -> str:
    """``prog POSITIONAL... --required X [options]``: one line, independent of the terminal."""
    parts = [prog]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction) or action.help == argparse.SUPPRESS:
            continue
        if not action.option_strings:
            parts.append(_invocation(action) if action.nargs not in ("*", argparse.REMAINDER)
                         else f"[{_metavar(action)} ...]")
        elif action.required:
            parts.append(_invocation(action))
    parts.append("[options]")
    return " ".join(parts)


def _options(parser: argparse.ArgumentParser, prog: str) -> list[str]:
    """One markdown line per option, grouped as ``--help`` groups them."""
    lines: list[str] = []
    for group in parser._action_groups:
        actions = [a for a in group._group_actions
                   if a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction)
                   and not isinstance(a, argparse._SubParsersAction)]
        if not actions:
            continue
        lines += ["", f"*{group.title}:*", ""]
        for action in actions:
            text = _help(action, prog)
            lines.append(f"- `{_invocation(action)}`" + (f": {text}" if text else ""))
    return lines


def _section(title: str, parser: argparse.ArgumentParser, prog: str, level: str = "##") -> list[str]:
    lines = [f"{level} `{title}`", ""]
    if parser.description:
        lines += [" ".join(parser.description.split()), ""]
    lines += ["```", _usage(parser, prog), "```"]
    return [*lines, *_options(parser, prog), ""]


def render() -> str:
    """The text of ``docs/cli.md`` as the parsers define it now."""
    sys.path.insert(0, str(ROOT))
    import app
    from blurcalib import cli
    from blurcalib.paper import alignment, generic, patterns, psf_quality, threshold_sweep

    parser = cli.build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    summaries = {a.dest: a.help for a in sub._choices_actions}
    lines = ["# Command-line options", "",
             "Written by `python scripts/cli_doc.py` from the parsers themselves: it says what `--help` "
             "says. `python -m blurcalib` is the same as `blurcalib`; every command reports bad input in "
             "one line and exits with status 2.", "",
             "| command | what it does |", "|---|---|"]
    for name in (*COMMANDS, "view"):
        anchor = "apppy-and-blurcalib-view" if name == "view" else f"blurcalib-{name}"
        lines.append(f"| [`blurcalib {name}`](#{anchor}) | {summaries[name]} |")
    lines.append("")
    for name in COMMANDS:
        lines += _section(f"blurcalib {name}", sub.choices[name], f"blurcalib {name}")
    modules = {"patterns": patterns, "alignment": alignment, "psf-quality": psf_quality,
               "threshold-sweep": threshold_sweep, "generic": generic}
    for name in EXPERIMENTS:
        exp = modules[name].build_parser()
        lines += _section(f"blurcalib experiment {name}", exp, exp.prog, level="###")
    lines += _section("app.py and blurcalib view", app.build_parser(), "python app.py")
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit with 1 when docs/cli.md is out of date")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        current = PAGE.read_text(encoding="utf-8") if PAGE.is_file() else ""
        if current != text:
            print(f"{PAGE.relative_to(ROOT)} is out of date: run python scripts/cli_doc.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text, encoding="utf-8")
    print(f"wrote {PAGE.relative_to(ROOT)} ({len(text.encode()) / 1000:.1f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
