"""Rarely used knobs as configuration keys, not command-line flags: `--config FILE` (TOML) or
`--config KEY=VALUE`, repeatable, later entries winning.

A subcommand declares a knob with `knob(parser, "--name", ...)`, with `add_argument`'s
arguments: its value reaches the command as `args.name` exactly as a flag's would (the same
converter, choices and default), but the parser takes no `--name` flag. One name, one
meaning: a key is spelt as the flag it replaces, without the dashes (`arc-loss`; `arc_loss`
reads the same), and converted by the flag's own type. A file is flat (its keys for the command
it is given to) or holds tables named by subcommand (`[calibrate]`, `[plan]`), so that one file
serves a whole cell; the running command reads its own table and refuses a key it does not
know, naming the file, the table and the closest key.

The flags a knob replaced still work for one release, with a warning naming the key
(`extract_moved`). Every key is listed by `jaxcal SUBCOMMAND --help` and in docs/config.md
(`reference`, kept in step by tests/test_cli_config.py).
"""

import argparse
import difflib
import re
import shutil
import sys
import textwrap
import tomllib
from pathlib import Path

#: `--config`'s help, the same in every subcommand.
HELP = (
    "a TOML file of configuration keys, or one KEY=VALUE; repeatable, later wins (the keys: below, "
    "and docs/config.md)"
)


class ConfigError(ValueError):
    """A configuration key or file that cannot be used: the message names the file, table and key."""


class _Knobs(argparse.ArgumentParser):
    """The knobs of one subcommand: a parser of their former flags whose errors are raised, not
    printed and exited on (the caller names the file or key)."""

    def error(self, message):
        raise ConfigError(message)


def knobs_of(parser: argparse.ArgumentParser) -> _Knobs | None:
    """`parser`'s knobs, or None when it has none."""
    return getattr(parser, "_jaxcal_knobs", None)


def knob(parser: argparse.ArgumentParser, name: str, **kwargs) -> None:
    """Declare the configuration key `name` (`--name`'s spelling) of `parser`'s subcommand, with
    `add_argument`'s keyword arguments; the first knob also adds `--config`."""
    knobs = knobs_of(parser)
    if knobs is None:
        knobs = _Knobs(prog=parser.prog, add_help=False, allow_abbrev=False)
        parser._jaxcal_knobs = knobs
        parser.add_argument("--config", action="append", default=[], metavar="FILE|KEY=VALUE", help=HELP)
    action = knobs.add_argument(name, **kwargs)
    parser.set_defaults(**{action.dest: action.default})
    # What is left of each action (its default in words) is for `--help`, not the namespace:
    # the knobs' parser parses into a namespace holding only what was given.
    action.help = action.help or action.dest.replace("_", " ")


def keys(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """`parser`'s configuration keys, by name (`arc-loss`), each with its action; a boolean
    pair (`--refine-intrinsics`/`--no-refine-intrinsics`) is one key."""
    knobs = knobs_of(parser)
    if knobs is None:
        return {}
    return {a.option_strings[0][2:]: a for a in knobs._actions}


def _bool(text: str, where: str) -> bool:
    value = text.strip().lower()
    if value in ("true", "yes", "on", "1"):
        return True
    if value in ("false", "no", "off", "0"):
        return False
    raise ConfigError(f"{where}: expected true or false, got {text!r}")


def _words(action: argparse.Action, value, where: str) -> list[str]:
    """`value` (TOML's, or KEY=VALUE's text) as the words its former flag would have taken."""
    flag = action.option_strings[0]
    if action.nargs == 0:  # store_true, or a --x/--no-x pair
        on = (
            value if isinstance(value, bool) else _bool(str(value), where) if isinstance(value, str) else None
        )
        if on is None:
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        if isinstance(action, argparse.BooleanOptionalAction):
            return [flag if on else "--no-" + flag[2:]]
        return [flag] if on == bool(action.const) else [_UNSET + action.dest]
    if isinstance(value, bool):
        raise ConfigError(f"{where}: expected a value, not {str(value).lower()}")
    if isinstance(action.nargs, int):  # a fixed number of values
        # KEY=[a,b,...] as the help and a TOML file write it, or KEY=a,b,...
        items = value if isinstance(value, list) else str(value).strip("[] ").replace(",", " ").split()
        return [flag, *(str(v) for v in items)]
    if isinstance(value, list):
        value = ",".join(str(v) for v in value)
    return [f"{flag}={value}"]


#: `_words`' word for a flag set back to its default (`false` for a flag that sets true).
_UNSET = "\0unset:"


def _close(name: str, known) -> str:
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


def _entries(command: str, known: dict, item: str, commands) -> list[tuple[str, object, str]]:
    """One `--config` entry as (key, value, where) triples."""
    path = Path(item)
    if path.is_file() or "=" not in item:
        try:
            data = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise ConfigError(f"--config {item}: no such file (and not a KEY=VALUE)") from None
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(f"--config {item}: cannot be read: {e}") from None
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"{item}: not TOML: {e}") from None
        tables = [k for k, v in data.items() if isinstance(v, dict)]
        if not tables:  # a flat file: keys of the command it is given to
            return [(k, v, f"{item}: {k}") for k, v in data.items()]
        loose = [k for k in data if k not in tables]
        if loose:
            raise ConfigError(
                f"{item}: {', '.join(loose)} outside a table; a file with [subcommand] tables holds every key in "
                "one (or has no tables at all, for the command it is given to)"
            )
        out = []
        for key in tables:
            if key not in commands:
                raise ConfigError(f"{item}: [{key}] is not a jaxcal subcommand{_close(key, commands)}")
            if key == command:
                out += [(k, v, f"{item}: [{key}] {k}") for k, v in data[key].items()]
        return out
    key, _, value = item.partition("=")
    return [(key.strip(), value, f"--config {item}")]


def apply(parser: argparse.ArgumentParser, args: argparse.Namespace, commands, given=()) -> None:
    """`args` with `--config`'s entries (in order) and then the former flags of `given`
    (`extract_moved`) set on it; a key the command does not take, or a value its converter
    refuses, is a `ConfigError` naming where it was."""
    known = keys(parser)
    knobs = knobs_of(parser)
    for item in getattr(args, "config", None) or []:
        for key, value, where in _entries(args.command, known, item, commands):
            name = key.replace("_", "-")
            if name not in known:
                what = "takes no configuration key" if not known else "has no configuration key"
                raise ConfigError(f"{where}: jaxcal {args.command} {what} {key}{_close(name, known)}")
            _parse(knobs, args, _words(known[name], value, where), where)
    for words in given:
        _parse(knobs, args, list(words), words[0].partition("=")[0])


def _parse(knobs: _Knobs, args: argparse.Namespace, words: list[str], where: str) -> None:
    if words and words[0].startswith(_UNSET):
        dest = words[0][len(_UNSET) :]
        setattr(args, dest, next(a.default for a in knobs._actions if a.dest == dest))
        return
    defaults = {a.dest: a.default for a in knobs._actions}
    for a in knobs._actions:
        a.default = argparse.SUPPRESS
    try:
        parsed = knobs.parse_args(words)
    except ConfigError as e:  # argparse names the flag ("argument --x: ..."); `where` names the key
        raise ConfigError(f"{where}: {re.sub(r'^argument [^:]+: ', '', str(e))}") from None
    finally:
        for a in knobs._actions:
            a.default = defaults[a.dest]
    for dest, value in vars(parsed).items():
        setattr(args, dest, value)


def extract_moved(
    parser: argparse.ArgumentParser, command: str, argv: list[str]
) -> tuple[list[str], list[str]]:
    """`argv` without the flags `command`'s knobs replaced, and those flags with their values
    (for `apply`), each named in a warning on stderr: they work for one release more."""
    knobs = knobs_of(parser)
    if knobs is None:
        return argv, []
    flags = {s: a for a in knobs._actions for s in a.option_strings}
    kept, moved, k = [], [], 0
    end = argv.index("--") if "--" in argv else len(argv)
    while k < len(argv):
        word = argv[k]
        name = word.partition("=")[0]
        action = flags.get(name) if k < end else None
        if action is None:
            kept.append(word)
            k += 1
            continue
        take = 0 if "=" in word or action.nargs == 0 else action.nargs if isinstance(action.nargs, int) else 1
        moved.append(argv[k : k + 1 + take])
        key = action.option_strings[0][2:]
        print(
            f"jaxcal: warning: `jaxcal {command} {name}` is now the configuration key {key} "
            f"(--config {key}=VALUE, or in a --config file); {name} goes in the next release",
            file=sys.stderr,
        )
        k += 1 + take
    return kept, moved


def epilog(parser: argparse.ArgumentParser) -> str | None:
    """The configuration keys for `--help`: one line each, with its default."""
    known = keys(parser)
    if not known:
        return None
    width = max(60, min(shutil.get_terminal_size().columns, 120) - 2)
    lines = ["configuration keys (--config KEY=VALUE, or KEY = VALUE in a --config TOML file):"]
    for name, action in known.items():
        text = f"{name} = {_metavar(action)}: {_help(action)}"
        lines += textwrap.wrap(text, width, initial_indent="  ", subsequent_indent="      ")
    return "\n".join(lines)


def _metavar(action: argparse.Action) -> str:
    if action.nargs == 0:
        return "true|false"
    if action.choices:
        return "|".join(str(c) for c in action.choices)
    if isinstance(action.metavar, tuple):
        return "[" + ", ".join(action.metavar) + "]"
    return action.metavar or "VALUE"


def _help(action: argparse.Action) -> str:
    text = (action.help or "").replace("%%", "%")
    if "default" in text.lower() or action.default in (None, False, argparse.SUPPRESS):
        return text
    default = action.default
    if isinstance(default, (list, tuple)):
        default = ",".join(str(v) for v in default)
    return f"{text} (default: {default})"


def reference(parsers: dict[str, argparse.ArgumentParser]) -> str:
    """docs/config.md's table of keys: per subcommand, every key, its values and what it does."""
    out = []
    for command, parser in parsers.items():
        known = keys(parser)
        if not known:
            continue
        out += [f"### `[{command}]`", "", "| key | value | what it does |", "| --- | --- | --- |"]
        for name, action in known.items():
            text = _help(action).replace("|", "\\|")
            out.append(f"| `{name}` | `{_metavar(action).replace('|', ' or ')}` | {text} |")
        out.append("")
    return "\n".join(out)
