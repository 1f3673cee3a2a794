"""Reading a configuration file, and refusing a key where it does not belong.

Theory of operation
-------------------
:func:`load_yaml` turns one YAML file into its top-level mapping, or a
:class:`~antireplay.core.errors.ConfigError` naming the file (missing, unreadable, not
YAML, not a mapping).  :func:`check_keys` walks that mapping against the model tree of
:class:`~antireplay.config.AppConfig` (every section, at any depth, through lists and
optional blocks) before any value is validated, so a key in the wrong place is refused
by name before a default could stand in for it: a key that exists elsewhere in the tree
says where it belongs (``max_age_s: not a top-level key; it belongs under dds:``), a typo
says which key it resembles, and a key of an earlier release says what replaced it.
Nothing here opens anything but the one file it is given.
"""

from __future__ import annotations

from pathlib import Path
from types import NoneType, UnionType
from typing import Any, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict

from antireplay.core.errors import ConfigError
from antireplay.core.settings import unknown_key


class Section(BaseModel):
    """What every block of the file is: strict types, no unknown key, frozen once loaded."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """A YAML file's top-level mapping, or ConfigError."""
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError.file_not_found("config", str(path)) from None
    except OSError as exc:
        raise ConfigError("file", str(path), f"a readable YAML file ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        raise ConfigError("file", str(path), f"valid YAML ({exc})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError("file", str(path), "a YAML mapping at the top level")
    return doc


def nested(annotation: Any) -> tuple[type[BaseModel] | None, bool]:
    """The model a field holds (and whether as a list of them), else ``(None, False)``;
    an optional block (``Model | None``) is its model."""
    args = get_args(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation, False
    if get_origin(annotation) in {Union, UnionType}:
        models = [a for a in args if a is not NoneType]
        return nested(models[0]) if len(models) == 1 else (None, False)
    if get_origin(annotation) is list and args:
        inner, _ = nested(args[0])
        return inner, inner is not None
    return None, False


def known_keys(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every key the file may hold, dotted (``keys[].kid`` for an entry of a list)."""
    found = []
    for name, field in model.model_fields.items():
        found.append(prefix + name)
        inner, many = nested(field.annotation)
        if inner is not None:
            found += known_keys(inner, f"{prefix}{name}{'[]' if many else ''}.")
    return found


def check_keys(
    model: type[BaseModel],
    data: Any,
    *,
    prefix: str = "",
    known: list[str] | None = None,
    renamed: dict[str, str] | None = None,
) -> None:
    """Refuse the first key of ``data`` (at any depth) that ``model`` does not hold there,
    saying where it belongs, what replaced it, or which key it resembles."""
    if known is None:
        known = known_keys(model)
    if not isinstance(data, dict):
        return  # pydantic names the wrong type
    for key, value in data.items():
        field = model.model_fields.get(str(key))
        dotted = prefix + str(key)
        if field is None:
            raise misplaced(dotted, known, renamed or {})
        inner, many = nested(field.annotation)
        if inner is None:
            continue
        if not many:
            check_keys(inner, value, prefix=f"{dotted}.", known=known, renamed=renamed)
        elif isinstance(value, list):
            for item in value:
                check_keys(inner, item, prefix=f"{dotted}[].", known=known, renamed=renamed)


def misplaced(dotted: str, known: list[str], renamed: dict[str, str]) -> ConfigError:
    """The error for an unknown key: renamed, elsewhere in the tree, or a near spelling."""
    if dotted in renamed:
        return ConfigError(dotted, dotted, f"no such key: it was renamed to {renamed[dotted]}")
    section, _, leaf = dotted.rpartition(".")
    homes = [k.rpartition(".")[0] for k in known if k.rpartition(".")[2] == leaf]
    if not homes:
        return unknown_key(dotted, known)
    where = f"a key of {section}:" if section else "a top-level key"
    blocks = " or ".join(f"{home}:" for home in homes if home)
    places = ["at the top level"] if "" in homes else []
    if blocks:
        places.append(f"under {blocks}")
    message = f"{dotted}: not {where}; it belongs {' or '.join(places)}"
    return ConfigError(dotted, dotted, "a known key", message=message)
