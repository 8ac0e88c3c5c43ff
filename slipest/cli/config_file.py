"""``--config FILE``: a command's options from a TOML file (``slipest serial --config rover.toml``).

The keys are the command's long options as spelt on the command line,
without the ``--`` (``_`` may stand for ``-``), and ``port`` for ``slipest
serial``'s PORT.  A rover's service file might read::

    # rover.toml, for: slipest serial --config rover.toml
    port = "/dev/ttyUSB0"
    legs = 4
    wheel = [0, 1]                       # a repeatable option takes a list
    rover = "rover.json"                 # slipest calibrate's file; paths are relative to this file's directory
    kS = 1000.0                          # the known soil (kS, phiS, phiD, dphi) [N/m, rad]
    record = "/var/lib/slipest/run.csv"
    log-level = "INFO"

and for ``slipest can``::

    interface = "socketcan"
    channel = "can0"
    bitrate = 500000
    bus-kwargs = { receive_own_messages = false }   # a table, or a list of "KEY=VALUE"

A value is checked as the command line checks it (its type, its choices);
a flag takes ``true`` or ``false``.  An option given on the command line
overrides the file's (a repeatable option's whole list, and ``-v``/``-q``).
An unknown key, a table where a value belongs, a value of the wrong type
or outside the choices, a file that cannot be read or is not TOML: each is
a :class:`ConfigFileError` naming the file and the key.
"""

from __future__ import annotations

import argparse
import difflib
import os
import tomllib

from slipest.cli.command import leg_count

#: Options whose value is a path: taken relative to the configuration file's directory.
PATH_OPTIONS = frozenset({"model", "rover", "record", "record_frames", "report"})
#: Options a file may give as a table ``{KEY = VALUE}`` (the keywords of the CAN bus).
TABLE_OPTIONS = frozenset({"bus_option"})
#: Options a file does not set.
NOT_IN_FILES = frozenset({"config", "help", "version"})


class ConfigFileError(ValueError):
    """A configuration file that cannot be used; the message names the file and the key."""


def file_keys(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The keys a configuration file may hold for the command ``parser`` parses -> their option."""
    keys = {}
    for action in parser._actions:  # argparse keeps its options there (no public accessor)
        if action.dest in NOT_IN_FILES or action.dest == argparse.SUPPRESS or action.help == argparse.SUPPRESS:
            continue
        if not action.option_strings:  # a positional: its name
            keys[action.dest] = action
        for flag in action.option_strings:
            if flag.startswith("--"):
                keys[flag[2:]] = action
    return keys


def _is_repeatable(action: argparse.Action) -> bool:
    return isinstance(action, (argparse._AppendAction, argparse._ExtendAction))


def _expected(action: argparse.Action) -> str:
    return {int: "an integer", float: "a number", leg_count: "a whole number of legs >= 1"}.get(action.type, "a value")


def _scalar(action: argparse.Action, value, fail):
    """One value as the command line would have produced it from its text."""
    if isinstance(value, (dict, list)):
        fail(f"expected a single value, got {'a table' if isinstance(value, dict) else 'a list'}")
    if isinstance(value, bool):
        fail(f"true/false is for flags; expected {_expected(action)}")
    if action.type in (int, leg_count) and isinstance(value, float):
        fail(f"expected {_expected(action)}, got {value!r}")
    text = str(value)
    try:
        out = action.type(text) if action.type is not None else text
    except (TypeError, ValueError, argparse.ArgumentTypeError) as exc:
        fail(f"expected {_expected(action)}, got {value!r}"
             + ("" if action.type in (int, float, leg_count) else f" ({exc})"))
    if action.choices is not None and out not in action.choices:
        fail(f"{value!r} is not one of {', '.join(map(str, action.choices))}")
    return out


def _convert(action: argparse.Action, value, fail):
    """The namespace value a file's ``value`` gives for ``action``."""
    if isinstance(action, argparse._StoreConstAction):  # flags: store_true, store_false, store_const
        if not isinstance(value, bool):
            fail(f"a flag takes true or false, got {value!r}")
        return action.const if value else action.default
    if isinstance(action, argparse._CountAction):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            fail(f"expected a count (0, 1, 2, ...), got {value!r}")
        return value
    if _is_repeatable(action):
        if isinstance(value, dict):
            if action.dest not in TABLE_OPTIONS:
                fail("expected a list, got a table")
            value = [f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in value.items()]
        items = value if isinstance(value, list) else [value]
        return [_scalar(action, v, fail) for v in items]
    return _scalar(action, value, fail)


def load_config_file(path: str, parser: argparse.ArgumentParser) -> dict:
    """The options a TOML file gives for the command ``parser`` parses: ``{dest: value}`` with values as
    the command line would give them (paths of :data:`PATH_OPTIONS` made relative to the file's directory).

    :class:`ConfigFileError` naming the file (and the key) when the file cannot be used.
    """
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigFileError(f"{path}: no such file") from None
    except OSError as exc:
        raise ConfigFileError(f"{path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigFileError(f"{path}: not valid TOML: {exc}") from None
    keys = file_keys(parser)
    base = os.path.dirname(os.path.abspath(path))
    out: dict = {}
    for key, value in doc.items():
        action = keys.get(key) or keys.get(key.replace("_", "-"))
        if action is None:
            near = difflib.get_close_matches(key, keys, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else f" (keys: {', '.join(sorted(keys))})"
            raise ConfigFileError(f"{path}: unknown key {key!r}{hint}")

        def fail(msg: str, key=key):
            raise ConfigFileError(f"{path}: key {key!r}: {msg}")

        converted = _convert(action, value, fail)
        if action.dest in PATH_OPTIONS and isinstance(converted, str):
            converted = os.path.join(base, os.path.expanduser(converted))
        elif action.dest in PATH_OPTIONS and isinstance(converted, list):  # a repeatable path (record)
            converted = [os.path.join(base, os.path.expanduser(c)) for c in converted]
        if action.dest in out and _is_repeatable(action):  # e.g. both bus-option and bus-kwargs
            converted = out[action.dest] + converted
        out[action.dest] = converted
    return out


def parse_with_config_file(parser: argparse.ArgumentParser, command_parser: argparse.ArgumentParser,
                           argv: list[str] | None, args: argparse.Namespace) -> argparse.Namespace:
    """``argv`` parsed again with the file ``args.config`` names as the command's defaults.

    ``parser``: the whole command line's parser; ``command_parser``: the
    subcommand's (whose options the file sets); ``args``: ``argv`` parsed
    without the file.  Options on the command line win; a repeatable option
    or a count (``-v``) given there replaces the file's value instead of
    adding to it.
    """
    values = load_config_file(args.config, command_parser)
    before = {dest: command_parser.get_default(dest) for dest in values}
    command_parser.set_defaults(**values)
    try:
        merged = parser.parse_args(argv)
    finally:
        command_parser.set_defaults(**before)
    for action in command_parser._actions:
        if action.dest in values and (_is_repeatable(action) or isinstance(action, argparse._CountAction)):
            given = getattr(args, action.dest)
            if given != before[action.dest]:  # given on the command line
                setattr(merged, action.dest, given)
    return merged
