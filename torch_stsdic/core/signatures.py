"""One parameter list per concept: a wrapper shows the signature of the function it wraps.

A thin public wrapper (``predicted_std`` around ``predicted_covariance``, ``track`` around
``plan_run``, ``track_distributed`` around ``track_distributed_many``) takes ``*args,
**kwargs`` and sets ``__signature__`` to :func:`signature_like` of the wrapped function, so
``help()``, IDEs and :func:`inspect.signature` show the real parameters, names and defaults,
while they are written down once. :func:`bind` checks a call against such a signature (the
same ``TypeError`` as a plain call) and returns every argument by name.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["signature_like", "param", "bind", "POSITIONAL", "KEYWORD"]

_KEEP: Any = object()
KEYWORD = inspect.Parameter.KEYWORD_ONLY
POSITIONAL = inspect.Parameter.POSITIONAL_OR_KEYWORD


def param(name: str, default: Any = inspect.Parameter.empty, annotation: Any = "Any", *,
          kind: Any = KEYWORD) -> inspect.Parameter:
    """A parameter to add with :func:`signature_like` (keyword-only by default)."""
    return inspect.Parameter(name, kind, default=default, annotation=annotation)


def signature_like(
    fn: Callable[..., Any],
    *,
    insert: Mapping[str, Sequence[inspect.Parameter]] | None = None,
    replace: Mapping[str, inspect.Parameter] | None = None,
    drop: Sequence[str] = (),
    positional: Sequence[str] = (),
    defaults: Mapping[str, Any] | None = None,
    returns: Any = _KEEP,
) -> inspect.Signature:
    """The signature of ``fn``, edited.

    Args:
        fn: the wrapped function.
        insert: name -> parameters inserted before it.
        replace: name -> the parameter that stands in its place.
        drop: names removed.
        positional: keyword-only names made positional-or-keyword (they move before the
            keyword-only ones, in order).
        defaults: name -> its new default.
        returns: the return annotation (default: that of ``fn``).
    """
    sig = inspect.signature(fn)
    insert, replace = dict(insert or {}), dict(replace or {})
    out: list[inspect.Parameter] = []
    for p in sig.parameters.values():
        out.extend(insert.get(p.name, ()))
        if p.name in drop:
            continue
        p = replace.get(p.name, p)
        if p.name in (defaults or {}):
            p = p.replace(default=defaults[p.name])  # type: ignore[index]
        out.append(p.replace(kind=POSITIONAL) if p.name in positional else p)
    out.sort(key=lambda p: p.kind)  # stable: only moves the new positional ones forward
    ret = sig.return_annotation if returns is _KEEP else returns
    return sig.replace(parameters=out, return_annotation=ret)


def bind(sig: inspect.Signature, *args: Any, **kwargs: Any) -> dict[str, Any]:
    """Every argument of a call by name, defaults filled in; ``TypeError`` (as for a plain
    call) on a missing, unknown or repeated argument."""
    ba = sig.bind(*args, **kwargs)
    ba.apply_defaults()
    return dict(ba.arguments)
