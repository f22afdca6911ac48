"""A scene's errors: the one type, and pydantic's validation errors as the scene's keys.

Every error names its file and its key, e.g. ``scene.toml: [material] nu: must be within [0,
0.49999], got 0.6``: :func:`describe` turns one pydantic error into that form, :func:`scene_error` makes one
of the scene's own.
"""

from __future__ import annotations

from .model_id import MODEL_ID_RULE

TABLES = ("mesh", "material", "boundary", "training", "registration")


class SceneError(ValueError):
    """A scene that cannot be used; the message names the file and the key."""


def scene_error(origin: str, key: str, message: str) -> SceneError:
    """The error of one key of the scene from `origin` (its file, or builtin:NAME)."""
    return SceneError(f"{origin}: {key}: {message}")


def key_of(loc: tuple) -> str:
    """A pydantic error location as the scene's key: ``[material] nu``, ``name``, ``[boundary]``."""
    if not loc:
        return ""
    head, rest = (f"[{loc[0]}]", loc[1:]) if loc[0] in TABLES else (str(loc[0]), loc[1:])
    key = ""
    for i, part in enumerate(rest):
        key += f"[{part}]" if isinstance(part, int) else (f".{part}" if i else str(part))
    return f"{head} {key}" if key else head


def describe(err: dict) -> str:
    """One pydantic error as 'key: what is wrong, got what'."""
    kind, ctx, loc = err["type"], err.get("ctx", {}), err["loc"]
    got = repr(err.get("input"))
    got = got if len(got) <= 60 else got[:57] + "..."
    table = len(loc) == 1 and loc[0] in TABLES
    if kind == "missing":
        what = "missing table" if table else "missing (required)"
    elif kind == "extra_forbidden":
        what = "unknown table" if isinstance(err.get("input"), dict) else "unknown key"
    elif kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        op, bound = {
            "greater_than": (">", "gt"),
            "greater_than_equal": (">=", "ge"),
            "less_than": ("<", "lt"),
            "less_than_equal": ("<=", "le"),
        }[kind]
        what = f"must be {op} {ctx[bound]}, got {got}"
    elif kind == "literal_error":
        what = f"must be {ctx['expected']}, got {got}"
    elif kind == "string_pattern_mismatch":
        what = f"{MODEL_ID_RULE}, got {got}"  # the name's, the only pattern
    elif kind == "value_error":
        what = str(ctx.get("error", err["msg"]))
    elif kind == "model_type" or kind == "dict_type":
        what = f"must be a table, got {got}"
    else:
        msg = err["msg"].replace("Input should be", "must be")
        msg = msg.replace("Tuple should", "must").replace("List should", "must")
        what = f"{msg}, got {got}"
    where = key_of(loc)
    if kind == "extra_forbidden" and len(loc) == 1 and isinstance(err.get("input"), dict):
        where = f"[{loc[0]}]"
    if kind == "value_error" and what.startswith("["):  # the message names its own key
        return what
    return f"{where}: {what}" if where else what
