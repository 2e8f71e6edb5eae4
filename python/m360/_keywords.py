"""Options written once: keyword lists whose entries carry their own check, help and CLI flag.

A keyword list is a ``TypedDict`` (``total=False``) whose every entry is annotated
``Annotated[T, Option(...)]``. The one list serves

- the signatures: ``def estimate(..., **keywords: Unpack[EstimateKeywords])``, so the type
  checker sees every keyword and its type;
- the documentation: :func:`document` appends each entry's help to the list's docstring;
- the checks: :func:`checked` runs each entry's ``check`` on the values given;
- the command line: :func:`add_flags` adds one flag per entry (``--name-with-dashes``) and
  :func:`from_args` reads them back as keywords.

So adding an option is one entry in one list (plus what the option does), wherever it is taken:
``m360.stitch``, ``m360.estimate``, ``m360.batch.run`` and ``m360 run`` all read the same lists
(docs/architecture.md, "Options").
"""

from __future__ import annotations

import argparse
import functools
import re
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "Option",
    "add_flags",
    "checked",
    "definition",
    "document",
    "from_args",
    "plain_text",
    "resolved",
    "split",
]


@dataclass(frozen=True)
class Option:
    """What one keyword means and how it is given on the command line.

    Attributes
    ----------
    help : str
        One sentence, also the flag's help.
    check : callable, optional
        ``check(value, name) -> value``: the value normalised, or an :class:`m360.InputError`.
        None: the option's consumer checks it (the stitching options: the core).
    parse : callable, optional
        The flag's argparse ``type`` (text → value).
    choices, nargs, metavar : optional
        As for ``argparse.add_argument``.
    flag : str, optional
        The flag's name when it is not ``--`` + the keyword with dashes; ``""``: no flag.
    aliases : tuple of str
        Other spellings of the flag.
    parts : mapping, optional
        A keyword whose value is a mapping given by one flag per key (``blend_options``:
        ``--poisson-lam`` …): key → the Option of that flag (its ``flag`` names it).
    default : object
        The value when the keyword is absent or None (:func:`resolved`); None: the consumer's.
    """

    help: str
    check: Callable[[Any, str], Any] | None = None
    parse: Callable[[str], Any] | None = None
    choices: Sequence[str] | None = None
    nargs: int | None = None
    metavar: str | tuple[str, ...] | None = None
    flag: str | None = None
    aliases: tuple[str, ...] = ()
    parts: Mapping[str, Option] = field(default_factory=dict)
    default: Any = None

    def flag_name(self, keyword: str) -> str:
        """The flag of this option when it is the keyword ``keyword``."""
        return self.flag if self.flag is not None else "--" + keyword.replace("_", "-")


@functools.cache
def definition(keywords: type) -> dict[str, Option]:
    """The entries of a keyword list in their order: keyword → :class:`Option`."""
    hints = typing.get_type_hints(keywords, include_extras=True)
    out: dict[str, Option] = {}
    for name, hint in hints.items():
        options = [m for m in getattr(hint, "__metadata__", ()) if isinstance(m, Option)]
        if len(options) != 1:
            raise TypeError(f"{keywords.__name__}.{name} needs exactly one Option annotation")
        out[name] = options[0]
    return out


def split(keywords: Mapping[str, Any], *lists: type, where: str) -> tuple[dict[str, Any], ...]:
    """Sort ``keywords`` into the given lists; None values are left out (None = the default).

    Raises
    ------
    TypeError
        For a keyword in none of the lists, as Python does for an unexpected keyword.
    """
    known = [definition(k) for k in lists]
    unknown = [name for name in keywords if not any(name in d for d in known)]
    if unknown:
        names = ", ".join(repr(n) for n in unknown)
        raise TypeError(f"{where}() got unexpected keyword argument(s) {names}")
    return tuple(
        {name: v for name, v in keywords.items() if name in d and v is not None} for d in known
    )


def checked(values: Mapping[str, Any], keywords: type) -> dict[str, Any]:
    """``values`` with each entry's ``check`` applied (entries without one pass as given)."""
    entries = definition(keywords)
    out = {}
    for name, value in values.items():
        check = entries[name].check
        out[name] = value if check is None or value is None else check(value, name)
    return out


def resolved(values: Mapping[str, Any], keywords: type) -> dict[str, Any]:
    """Every entry of ``keywords``: its checked value in ``values``, else its default."""
    given = checked({k: v for k, v in values.items() if v is not None}, keywords)
    return {name: given.get(name, o.default) for name, o in definition(keywords).items()}


def document(keywords: type) -> type:
    """Append a numpy-style list of the entries to the docstring of ``keywords``; return it."""
    lines = []
    for name, option in definition(keywords).items():
        default = "" if option.default is None else f" Default {option.default!r}."
        lines += [f"{name}", f"    {option.help}.{default}"]
    doc = (keywords.__doc__ or "").rstrip()
    keywords.__doc__ = f"{doc}\n\n    Keywords\n    --------\n" + "".join(
        f"    {line}\n" for line in lines
    )
    return keywords


def add_flags(parser: argparse.ArgumentParser | Any, keywords: type) -> None:
    """Add one flag per entry of ``keywords`` to ``parser`` (or an argument group).

    Every flag defaults to None (not given: the API's default applies); its ``dest`` is the
    keyword (``part__key`` for the flags of a mapping keyword).
    """
    for name, option in definition(keywords).items():
        if option.parts:
            for key, part in option.parts.items():
                _add(parser, part, f"{name}__{key}", part.flag_name(key))
        elif option.flag != "":
            _add(parser, option, name, option.flag_name(name))


def _add(parser: Any, option: Option, dest: str, flag: str) -> None:
    # argparse formats help with %: a literal one is doubled.
    help_text = plain_text(option.help).replace("%", "%%")
    kwargs: dict[str, Any] = {"dest": dest, "default": None, "help": help_text}
    if option.parse is not None:
        kwargs["type"] = option.parse
    for key in ("choices", "nargs", "metavar"):
        if getattr(option, key) is not None:
            kwargs[key] = getattr(option, key)
    if option.metavar is None and option.choices is None:
        kwargs["metavar"] = dest.rpartition("__")[2].upper()  # LAM, not BLEND_OPTIONS__LAM
    parser.add_argument(flag, *option.aliases, **kwargs)


def from_args(args: argparse.Namespace, keywords: type) -> dict[str, Any]:
    """The keywords that the flags of ``keywords`` gave (those left out are not in the dict)."""
    out: dict[str, Any] = {}
    for name, option in definition(keywords).items():
        if option.parts:
            parts = {k: getattr(args, f"{name}__{k}", None) for k in option.parts}
            given = {k: v for k, v in parts.items() if v is not None}
            if given:
                out[name] = given
        else:
            value = getattr(args, name, None)
            if value is not None:
                out[name] = tuple(value) if isinstance(value, list) else value
    return out


_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(text: str) -> str:
    """``text`` without reStructuredText markup, for a terminal: ``:func:`x``` and ````x```` → x."""
    return _LITERAL.sub(r"\1", _ROLE.sub(r"\1", text))
