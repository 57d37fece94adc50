"""Command-line helpers for a newcomer: "did you mean", readable errors, progress bars.

* :class:`HelpfulParser` — an ``argparse.ArgumentParser`` whose errors for an
  unknown command, choice or option end with the closest valid one.
* :func:`format_error` — an exception as one line (``mems-stereo CMD: error:
  ...``) with the advice, where the message carries one after a newline, on a
  second line; long messages are cut (``-v`` prints them whole).
* :func:`progress_bar` — a tqdm bar on stderr, off under ``-q`` and when
  stderr is not a terminal.
"""

from __future__ import annotations

import argparse
import difflib
import re
import sys

#: characters of an error's first line before it is cut (``-v``: never cut)
MAX_ERROR_CHARS = 300


def suggest(word: str, choices) -> str | None:
    """The closest of ``choices`` to ``word`` (difflib, cutoff 0.6), or None."""
    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return close[0] if close else None


class HelpfulParser(argparse.ArgumentParser):
    """ArgumentParser that adds "did you mean ..." to invalid-choice and unknown-option errors."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        #: the action ``add_subparsers`` returned (its ``choices``: name -> subparser)
        self.subcommands = None

    def add_subparsers(self, **kwargs):
        self.subcommands = super().add_subparsers(**kwargs)
        return self.subcommands

    def all_option_strings(self) -> list[str]:
        """Every ``--option`` of this parser and of its subcommands (parse_args reports
        a subcommand's unknown options at the top)."""
        opts = [s for s in self._option_string_actions if s.startswith("--")]
        if self.subcommands is not None:
            for sub in self.subcommands.choices.values():
                if isinstance(sub, HelpfulParser):
                    opts += sub.all_option_strings()
        return sorted(set(opts))

    def parse_known_args(self, args=None, namespace=None):  # noqa: D102 - remembers args
        self.last_args = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def command_parser(self) -> tuple[str, HelpfulParser]:
        """The (sub)command the last parsed command line names, and its parser
        (``plot acquisition``: the figure's); ``("", self)`` when it names none."""
        words, parser = [], self
        for a in getattr(self, "last_args", []):
            subs = parser.subcommands.choices if parser.subcommands is not None else {}
            if a in subs and isinstance(subs[a], HelpfulParser):
                words.append(a)
                parser = subs[a]
        return " ".join(words), parser

    def commands_with(self, option: str) -> list[str]:
        """The subcommands (``plot acquisition`` for figures) that take ``option``."""
        if self.subcommands is None:
            return []
        out = []
        for name, sub in self.subcommands.choices.items():
            if not isinstance(sub, HelpfulParser):
                continue
            if option in sub._option_string_actions:
                out.append(name)
            out += [f"{name} {x}" for x in sub.commands_with(option)]
        return out

    def option_hint(self, word: str) -> str | None:
        """The advice for an unrecognised argument ``word`` (None for a non-option):
        the nearest option of the command named, else the commands that take that
        option (or its nearest) — never the word itself."""
        if not word.startswith("-"):
            return None
        name = word.split("=")[0]
        cmd, parser = self.command_parser()
        here = f"not of {cmd}" if cmd else "not of mems-stereo itself"
        if name in self.all_option_strings():  # a real option, of other commands
            return f"{name} is an option of {_listed(self.commands_with(name))}, {here}"
        own = [o for o in parser._option_string_actions if o.startswith("--")]
        s = suggest(name, own) if parser is not self else None
        if s:
            return f"did you mean {s} (not {name})?"
        s = suggest(name, self.all_option_strings())
        if not s:
            return None
        return f"did you mean {s} (an option of {_listed(self.commands_with(s))}, {here})?"

    def error(self, message: str):  # noqa: D102 - argparse's hook
        hint = None
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2)) or [
                c.strip() for c in m.group(2).split(",")]
            s = suggest(m.group(1), choices)
            hint = f"did you mean '{s}'?" if s else None
        m = re.search(r"unrecognized arguments: (.*)", message)
        if m:
            hints = [h for h in map(self.option_hint, m.group(1).split()) if h]
            hint = " ".join(hints) or None
        # one line (no usage block): what is wrong, and where to look
        cmd = self.command_parser()[0] if m else ""
        text = (f"{self.prog}: error: {' '.join(message.split())} "
                f"(see {self.prog}{' ' + cmd if cmd else ''} --help)")
        if hint:
            text += f"\n  {hint}"
        self.exit(2, text + "\n")


def examples(mod) -> list[str]:
    """A command module's example command lines (``EXAMPLE``: a string or a list)."""
    ex = mod.EXAMPLE
    return [ex] if isinstance(ex, str) else list(ex)


def epilog(lines: list[str]) -> str:
    """The ``--help`` epilog: one example command per line."""
    return ("examples (run in order from any folder):\n" if len(lines) > 1 else "example:\n") \
        + "\n".join("  " + x for x in lines)


#: advice for errors whose message carries none, by exception class name
ADVICE = {
    "NotObservableError": "record the target at more distances (three or more), give the "
                          "measured distances (--target-distances-file), or --fix the parameters "
                          "named; --allow-unobservable holds them at their nominal values",
}


def format_error(command: str | None, exc: BaseException, verbose: bool = False) -> str:
    """``mems-stereo CMD: error: <first line>`` plus the advice line(s), if any.

    A message's first line is what went wrong; further lines are advice
    (the package's convention).  The first line is cut to
    ``MAX_ERROR_CHARS`` unless ``verbose``.
    """
    text = str(exc).strip() or type(exc).__name__
    first, _, rest = text.partition("\n")
    if not rest:
        rest = ADVICE.get(type(exc).__name__, "")
    if not verbose and len(first) > MAX_ERROR_CHARS:
        first = first[:MAX_ERROR_CHARS - 1].rstrip() + "…"
        rest = (rest + "\n" if rest else "") + "(-v prints the whole message)"
    prog = f"mems-stereo {command}" if command else "mems-stereo"
    lines = [f"{prog}: error: {first}"]
    lines += ["  " + r.strip() for r in rest.splitlines() if r.strip()]
    return "\n".join(lines)


def progress_bar(total, desc: str, unit: str = "shot", quiet: bool = False):
    """A tqdm progress bar on stderr; disabled under ``-q`` or when stderr is not a terminal
    (then a :class:`_NoBar`, and tqdm is not imported: it would slow a short run's start)."""
    if quiet or not sys.stderr.isatty():
        return _NoBar(total)
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False,
                dynamic_ncols=True)


class _NoBar:
    """A disabled progress bar: counts ``update`` calls, ``write`` prints, every other
    tqdm method does nothing."""

    def __init__(self, total=None):
        self.total = total
        self.n = 0

    def update(self, n=1):
        self.n += n

    def write(self, s, file=None, end="\n", nolock=False):
        print(s, file=sys.stdout if file is None else file, end=end)

    def __getattr__(self, name):  # close, refresh, set_postfix_str, set_description, ...
        if name.startswith("__"):
            raise AttributeError(name)
        return lambda *args, **kwargs: None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class StatusProgress:
    """A progress bar for a step whose length is unknown (calibration rounds).

    Call it with a status line: the bar shows the line and counts the calls;
    ``verbose`` also prints it (``-v``).  Use as a context manager.
    """

    def __init__(self, desc: str, quiet: bool = False, verbose: bool = False):
        self.bar = progress_bar(None, desc, unit="step", quiet=quiet)
        self.verbose = verbose and not quiet

    def __call__(self, line: str) -> None:
        if self.verbose:
            self.bar.write(str(line), file=sys.stdout)
        self.bar.set_postfix_str(str(line)[:60], refresh=False)
        self.bar.update(1)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.bar.close()
        return False


def _listed(names: list[str]) -> str:
    """``['a']`` -> ``a``; ``['a', 'b', 'c']`` -> ``a, b and c``."""
    return " and ".join([", ".join(names[:-1]), names[-1]]) if len(names) > 1 else names[0]
