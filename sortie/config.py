"""Configuration of every ``sortie`` command from a file and the environment.

Each long option of each command may also come from

- an environment variable ``SORTIE_<COMMAND>_<OPTION>``: the command path and
  the option in upper case, dashes as underscores (``sortie terrain serve
  --max-workers 8`` = ``SORTIE_TERRAIN_SERVE_MAX_WORKERS=8``; ``sortie server
  --port`` = ``SORTIE_SERVER_PORT``); a list option (``--dem A B``) takes a
  shell-quoted list, a flag (``--no-record``) 1/true/yes/on or 0/false/no/off;
- a TOML file given by ``sortie --config FILE`` or ``SORTIE_CONFIG``: one table
  per command path (``[server]``, ``[terrain.serve]``, ``[dis]``) whose keys are
  the long options (``max-workers`` or ``max_workers``), with TOML types; the
  global options (``log-format``, ``verbose``) at the top level.

Precedence, as in most Unix daemons: the command line, then the environment,
then the file, then the built-in default; within a group of alternatives
(``--dem | --terrain``) too: the alternative of the highest of these wins, and
two alternatives of one group (``--cell | --bbox``, ``--record | --no-record``)
from the same one are an error naming both and where each came from, as the
command line's "not allowed with". An option abbreviated on
the command line (``--de`` for ``--dem``, as argparse allows) counts as given
there. Values are checked like command-line
ones (the option's type and choices); a bad one, an unknown table or an unknown
key is an error naming where it came from, so a typo in a deployment fails at
start rather than being ignored. This is what docker-compose.yml's
``environment:`` sections use (docs/DEPLOYMENT.md).
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import tomllib
from pathlib import Path

from sortie.errors import InvalidArgument

ENV_PREFIX = "SORTIE_"
TRUE_WORDS = ("1", "true", "yes", "on")
FALSE_WORDS = ("0", "false", "no", "off")
# The longest --grace-s a service takes: seconds in-flight calls get after SIGTERM (Docker's
# stop_grace_period of 15-30 s is what bounds it in practice).
MAX_GRACE_S = 600.0
# Where an option's value came from when not from the command line (action.sortie_layer).
ENVIRONMENT, FILE = "environment", "file"


def env_name(command_path: tuple[str, ...], dest: str) -> str:
    """The environment variable of option ``dest`` (argparse's destination) of a command
    (``()``: the global options, e.g. SORTIE_LOG_FORMAT)."""
    return ENV_PREFIX + "_".join(p.replace("-", "_").upper() for p in (*command_path, dest))


def command_parsers(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    """(command path, parser) of every (sub-)command below ``parser``, depth first."""
    for action in parser._actions:  # noqa: SLF001 - argparse has no public walk of its sub-parsers
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            for name, sub in action.choices.items():
                yield (*path, name), sub
                yield from command_parsers(sub, (*path, name))


def port_number(text: str) -> int:
    """An argparse type: a TCP/UDP port, 0 ..= 65535 (0: the system picks a free one).
    Python's sockets and gRPC take any int and keep its low 16 bits, so a typo like 70000
    would otherwise serve quietly on port 4464."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port is an integer 0 ..= 65535, got {text!r}") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 ..= 65535, got {value}")
    return value


def grace_seconds(text: str) -> float:
    """An argparse type: --grace-s, the seconds in-flight calls get on shutdown, a finite
    number in [0, MAX_GRACE_S] (gRPC's stop takes any float: inf overflowed at SIGTERM, nan
    and negative values passed)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds (got {text!r})") from None
    if not (math.isfinite(value) and 0.0 <= value <= MAX_GRACE_S):
        raise argparse.ArgumentTypeError(f"must be within [0, {MAX_GRACE_S:g}] s (got {text!r})")
    return value


def bound_ports(parser: argparse.ArgumentParser) -> None:
    """Every integer option named like a port (--port, --metrics-port) of every command
    takes :func:`port_number`."""
    for _, sub in command_parsers(parser):
        for action in sub._actions:  # noqa: SLF001
            if action.dest == "port" or action.dest.endswith("_port"):
                if action.type is int:
                    action.type = port_number


def _options(parser: argparse.ArgumentParser) -> dict:
    """dest -> action of the long options a file or the environment may set."""
    return {a.dest: a for a in parser._actions  # noqa: SLF001
            if a.option_strings and any(o.startswith("--") for o in a.option_strings)
            and not isinstance(a, (argparse._HelpAction, argparse._VersionAction))}  # noqa: SLF001


def _converted(action: argparse.Action, value, source: str):
    """``value`` (a string from the environment, or a TOML value) as the option would parse it."""
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):  # noqa: SLF001
        if isinstance(value, bool):
            flag = value
        elif str(value).lower() in TRUE_WORDS + FALSE_WORDS:
            flag = str(value).lower() in TRUE_WORDS
        else:
            raise InvalidArgument(source, f"must be one of {'/'.join(TRUE_WORDS)} or {'/'.join(FALSE_WORDS)}",
                                  value=value)
        return flag if isinstance(action, argparse._StoreTrueAction) else not flag  # noqa: SLF001
    if isinstance(action, argparse._CountAction):  # noqa: SLF001 - -v/-vv: a count, 0 or more
        try:
            count = int(value) if not isinstance(value, (bool, float)) else None
        except ValueError:
            count = None
        if count is None or count < 0:
            raise InvalidArgument(source, "must be a count, 0 or more", value=value)
        return count
    many = action.nargs in ("+", "*") or isinstance(action.nargs, int) and action.nargs > 1
    if many:
        items = shlex.split(value) if isinstance(value, str) else list(value) if isinstance(value, list) else [value]
    else:
        items = [value]
    out = []
    for item in items:
        if action.type in (int, float) and not isinstance(item, str):  # a TOML number
            if isinstance(item, bool) or not isinstance(item, (int, float)) or (
                    action.type is int and not isinstance(item, int)):
                raise InvalidArgument(source, f"must be {'an integer' if action.type is int else 'a number'}",
                                      value=item)
            item = action.type(item)
        else:
            item = item if isinstance(item, str) else str(item)
            if action.type is not None:
                try:
                    item = action.type(item)
                except (TypeError, ValueError, argparse.ArgumentTypeError) as exc:
                    why = {int: "must be an integer", float: "must be a number"}.get(action.type, str(exc))
                    shown = None if isinstance(exc, argparse.ArgumentTypeError) else item  # its text shows it
                    raise InvalidArgument(source, why or "has the wrong type", value=shown) from None
        if action.choices is not None and item not in action.choices:
            raise InvalidArgument(source, f"must be one of {', '.join(map(str, action.choices))}", value=item)
        out.append(item)
    return out if many else out[0]


def read_config_file(path: str | os.PathLike) -> dict:
    """The TOML file's tables (InvalidArgument naming the file when it cannot be read)."""
    p = Path(path)
    try:
        return tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InvalidArgument("--config", "no such file", value=str(p)) from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise InvalidArgument("--config", f"cannot be read: {exc}", value=str(p)) from None


def _table(config: dict, path: tuple[str, ...]) -> dict | None:
    table = config
    for part in path:
        table = table.get(part) if isinstance(table, dict) else None
        if table is None:
            return None
    return table


def _check_tables(table: dict, commands: dict, where: str, path: tuple = ()) -> None:
    """Every key of the table of command ``path`` is an option of it or a sub-command's table."""
    options = {d.replace("_", "-") for d in _options(commands[path])}
    for key, value in table.items():
        sub_path = (*path, key)
        if sub_path in commands:
            if not isinstance(value, dict):
                raise InvalidArgument(f"{where}: {'.'.join(sub_path)}", "must be a table of options")
            _check_tables(value, commands, where, sub_path)
        elif key.replace("_", "-") not in options:
            raise InvalidArgument(f"{where}: {'.'.join(sub_path)}",
                                  f"is not an option of sortie{''.join(' ' + p for p in path)}")


def apply(parser: argparse.ArgumentParser, config_path: str | None = None, environ=None,
          strict: bool = True) -> None:
    """Set the defaults of every command's options from the environment and the config
    file (see the module docstring); an option given so is no longer required on the
    command line. ``strict``: refuse tables and keys that name no command or option
    (False when ``parser`` holds only the command being run: the others' tables are
    not its business)."""
    environ = os.environ if environ is None else environ
    config_path = config_path or environ.get(ENV_PREFIX + "CONFIG")
    config = read_config_file(config_path) if config_path else {}
    commands = {(): parser, **dict(command_parsers(parser))}  # () = the global options
    if strict:
        _check_tables(config, commands, str(config_path))
    else:  # only the tables of the commands at hand, and the global options
        for path in commands:
            table = _table(config, path) if path else {k: v for k, v in config.items() if not isinstance(v, dict)}
            if isinstance(table, dict):
                _check_tables(table, commands, str(config_path), path)
    for path, sub in commands.items():
        table = _table(config, path) or {}
        for dest, action in _options(sub).items():
            if not path and dest == "config":
                continue
            name = env_name(path, dest)
            if name in environ:
                value = _converted(action, environ[name], name)
                source, layer = name, ENVIRONMENT
            else:
                key = next((k for k in (dest, dest.replace("_", "-")) if k in table and not isinstance(table[k], dict)),
                           None)
                if key is None:
                    continue
                source, layer = f"{config_path}: {'.'.join(path)}.{key}", FILE
                value = _converted(action, table[key], source)
            if not hasattr(action, "sortie_builtin_default"):
                action.sortie_builtin_default = action.default
            action.default = value
            action.required = False
            action.sortie_source = source
            action.sortie_layer = layer
        # argparse checks a required group of alternatives (--cell | --bbox) against the command
        # line alone: one given here satisfies it (settle_exclusive then sees to the rest).
        for group in sub._mutually_exclusive_groups:  # noqa: SLF001 - argparse keeps no public list
            if group.required and any(_configured(a) for a in group._group_actions):  # noqa: SLF001
                group.required = False


def _configured(action: argparse.Action) -> bool:
    """Whether the environment or the config file gave ``action`` a value of its own (a flag
    set to its default, SORTIE_..._NO_RECORD=0, gives none)."""
    return bool(getattr(action, "sortie_source", None)) and action.default != action.sortie_builtin_default


def source_of(parser: argparse.ArgumentParser, argv: list[str], field: str, value=None) -> str | None:
    """Where option ``field`` (its dest, or its --name) got its value when not from the command
    line: the environment variable or the config file's key; None otherwise (and None when
    ``value``, the value an error is about, is not the option's value: the error is about
    something else of the same name). A value a command checks after parsing is then named by
    its source, as argparse's own checks name it."""
    name = field.lstrip("-").replace("-", "_")
    given = command_line_actions(parser, argv)
    for sub in _active_parsers(parser, argv):
        for action in sub._actions:  # noqa: SLF001
            if (action.dest == name and getattr(action, "sortie_source", None) and action not in given
                    and not getattr(action, "sortie_overridden", False)
                    and (value is None or _same_value(value, action.default))):
                return action.sortie_source
    return None


def _same_value(value, option_value) -> bool:
    """Whether an error's ``value`` is the option's value (or one of a list option's)."""
    candidates = option_value if isinstance(option_value, (list, tuple)) else [option_value]
    return value == option_value or any(
        value == c or str(value) == str(c) or isinstance(c, str) and os.path.normpath(str(value)) == os.path.normpath(c)
        for c in candidates)


def settle_exclusive(parser: argparse.ArgumentParser, args: argparse.Namespace, argv: list[str]) -> None:
    """Precedence within a group of alternatives: the command line's member (``--dem`` over a
    ``SORTIE_SERVER_TERRAIN`` from the environment), else the environment's (over a config
    file's); the other members go back to their built-in defaults. Two members of a group, required
    or not (``--dem`` and ``--terrain``, ``--record`` and ``--no-record``), from the same environment
    or file are an InvalidArgument naming both and where each came from (the command line's two
    are argparse's own error); one from a lower layer is overridden, not an error."""
    given = command_line_actions(parser, argv)
    for sub in _active_parsers(parser, argv):
        for group in sub._mutually_exclusive_groups:  # noqa: SLF001 - argparse keeps no public list
            members = group._group_actions  # noqa: SLF001
            chosen = [a for a in members if a in given]
            if not chosen:
                configured = [a for a in members if _configured(a)]
                layer = ENVIRONMENT if any(a.sortie_layer == ENVIRONMENT for a in configured) else FILE
                chosen = [a for a in configured if a.sortie_layer == layer]
                if len(chosen) > 1:  # argparse's "not allowed with", as the command line would say it
                    a, b = chosen[:2]
                    raise InvalidArgument(f"{_option_name(a)} (set by {a.sortie_source})",
                                          f"not allowed with {_option_name(b)} (set by {b.sortie_source}): "
                                          "give one of them")
            for a in members:
                if a not in chosen and hasattr(a, "sortie_builtin_default"):
                    setattr(args, a.dest, a.sortie_builtin_default)
                    a.sortie_overridden = True


def _option_name(action: argparse.Action) -> str:
    return next((o for o in action.option_strings if o.startswith("--")), action.dest)


_NOT_GIVEN = object()


def command_line_actions(parser: argparse.ArgumentParser, argv: list[str]) -> set:
    """The actions the command line ``argv`` gives, as argparse itself reads it (an option
    abbreviated, ``--de`` for ``--dem``, or as ``--dem=FILE``, included): ``argv`` parsed once
    more with every long option's default set to a marker, which any value given replaces."""
    parsers = _active_parsers(parser, argv)
    actions = [a for sub in parsers for a in _options(sub).values()]
    saved = [(a, a.default) for a in actions]
    try:
        for a in actions:  # a count or an append starts from None, not from a marker
            counted = isinstance(a, (argparse._CountAction, argparse._AppendAction))  # noqa: SLF001
            a.default = None if counted else _NOT_GIVEN
        namespace, _ = parser.parse_known_args(argv)
    finally:
        for a, default in saved:
            a.default = default
    out = set()
    for a in actions:
        got = getattr(namespace, a.dest, _NOT_GIVEN)
        counted = isinstance(a, (argparse._CountAction, argparse._AppendAction))  # noqa: SLF001
        if got is not (None if counted else _NOT_GIVEN) and got is not _NOT_GIVEN:
            out.add(a)
    return out


def _active_parsers(parser: argparse.ArgumentParser, argv: list[str]) -> list:
    """The parser and the sub-command parsers ``argv`` names, outermost first."""
    out, rest = [parser], list(argv)
    while True:
        subs = [a for a in out[-1]._actions if isinstance(a, argparse._SubParsersAction)]  # noqa: SLF001
        k = next((i for i, w in enumerate(rest) if subs and w in subs[0].choices), None)
        if k is None:
            return out
        out.append(subs[0].choices[rest[k]])
        rest = rest[k + 1:]
