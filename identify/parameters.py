"""Parameter sets of a model, in the spirit of lmfit's ``Parameters``.

Values are SI.  A parameter is addressed by its stable name (``theta4``) or its alias
(``area``).  START.json files, RESULT.json files and flat ``{name: value}`` objects all
load into a :class:`Parameters`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from identify.errors import InputError
from identify.model import CompiledModel

# What a parameter's entry may hold: START.json's own keys and what RESULT.json adds
# (so that a result restarts a fit as it is).
ENTRY_KEYS = frozenset({"value", "prior_std", "min", "max", "std", "std_residual", "estimated", "unit", "alias",
                        "at_bound", "initial"})

class ParameterError(InputError):
    """A parameter file or name that does not fit the model."""


@dataclass
class Parameter:
    """One parameter: its value, whether it is estimated, and its prior standard deviation."""

    name: str
    alias: str
    unit: str
    value: float
    nominal: float
    vary: bool = False
    prior_std: float | None = None  # None: a scale-aware default (see estimator)
    minimum: float | None = None  # bounds the estimator respects; None: unbounded
    maximum: float | None = None
    physical: tuple[float | None, float | None] = (None, None)  # the declaration's bounds
    # Where the fit that wrote this value started (a RESULT.json's "initial"): a restart
    # reports the original start, not the point it went on from.
    initial: float | None = None

    def at_bound(self) -> str | None:
        """"minimum" or "maximum" where the value sits on that bound, else None."""
        if self.minimum is not None and self.value <= self.minimum:
            return "minimum"
        if self.maximum is not None and self.value >= self.maximum:
            return "maximum"
        return None


class Parameters:
    """Ordered parameters of one model."""

    def __init__(self, model: CompiledModel, values: dict[str, float] | None = None):
        self.model_name = model.name
        self._items = [Parameter(p.name, p.alias, p.unit, p.nominal, p.nominal, minimum=p.minimum, maximum=p.maximum,
                                 physical=(p.minimum, p.maximum)) for p in model.parameter_specs]
        self._index = {}
        for i, p in enumerate(self._items):
            self._index[p.name] = i
            if p.alias:
                self._index[p.alias] = i
        for k, v in (values or {}).items():
            self[k].value = float(v)

    def __getitem__(self, key: str) -> Parameter:
        try:
            return self._items[self._index[key]]
        except KeyError:
            known = ", ".join(p.name for p in self._items)
            raise ParameterError(f"model {self.model_name!r} has no parameter {key!r} (known: {known})") from None

    def __contains__(self, key: str) -> bool:
        return key in self._index

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def names(self) -> list[str]:
        return [p.name for p in self._items]

    def index(self, key: str) -> int:
        self[key]
        return self._index[key]

    def vector(self) -> np.ndarray:
        return np.array([p.value for p in self._items], dtype=float)

    def set_vector(self, values: np.ndarray) -> None:
        for p, v in zip(self._items, values, strict=True):
            p.value = float(v)

    def varying(self) -> list[str]:
        return [p.name for p in self._items if p.vary]

    def set_estimated(self, keys: list[str]) -> None:
        """Estimate exactly these parameters (names or aliases), fix all others."""
        idx = {self.index(k) for k in keys}
        for i, p in enumerate(self._items):
            p.vary = i in idx

    def copy(self) -> Parameters:
        new = Parameters.__new__(Parameters)
        new.model_name = self.model_name
        new._items = [Parameter(**vars(p)) for p in self._items]
        new._index = dict(self._index)
        return new

    def as_dict(self) -> dict[str, float]:
        return {p.name: p.value for p in self._items}

    # ----------------------------------------------------------------------------------
    @classmethod
    def from_file(cls, model: CompiledModel, path: str | Path) -> Parameters:
        """Load START.json, RESULT.json (``RESULT.json#LABEL``: one experiment of a
        --per-experiment result) or a flat ``{name: value}`` object."""
        doc, source = load_document(path)
        return cls.from_document(model, doc, source=source)

    @classmethod
    def from_document(cls, model: CompiledModel, doc: Any, source: str = "parameters") -> Parameters:
        if not isinstance(doc, dict):
            raise ParameterError(f"{source}: expected a JSON object")
        declared = doc.get("model")
        if isinstance(declared, str) and declared != model.name:
            raise ParameterError(f"{source}: parameters are for model {declared!r}, not {model.name!r}")
        body = doc.get("parameters", doc if "model" not in doc else {})
        if not isinstance(body, dict):
            raise ParameterError(f"{source}: 'parameters' must be an object of name: value")
        if isinstance(doc.get("per_experiment"), dict) and "parameters" not in doc:
            labels = ", ".join(doc["per_experiment"]) or "none"
            raise ParameterError(f"{source}: a --per-experiment result holds one parameter set per experiment "
                                 f"({labels}), not one: name the one to use as {source}#LABEL")
        if "model" in doc and "parameters" not in doc:
            raise ParameterError(f"{source}: no 'parameters' in this file (a RESULT.json or START.json has them)")
        params = cls(model)
        for key, raw in body.items():
            if key in ("model", "format"):
                continue
            if key not in params:
                raise ParameterError(f"{source}: unknown parameter {key!r} for model {model.name!r}")
            prior = None
            value = raw
            p = params[key]
            if isinstance(raw, dict):  # RESULT.json entry or {"value", "prior_std", "min", "max"}
                unknown = sorted(set(raw) - ENTRY_KEYS)
                if unknown:
                    # A misspelt bound ("minimum") would otherwise be dropped without a word.
                    raise ParameterError(f"{source}: parameter {key!r} has unknown key {unknown[0]!r} "
                                         f"(known: value, prior_std, min, max)")
                value = raw.get("value")
                prior = raw.get("prior_std")
                initial = raw.get("initial")
                if initial is not None:
                    if not isinstance(initial, (int, float)) or isinstance(initial, bool) or not math.isfinite(initial):
                        raise ParameterError(f"{source}: initial of {key!r} must be a finite number, got {initial!r}")
                    p.initial = float(initial)
                for bound in ("min", "max"):
                    if raw.get(bound) is not None:
                        _set_bound(p, bound, raw[bound], source)
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
                raise ParameterError(f"{source}: parameter {key!r} must be a finite number, got {value!r}")
            p.value = float(value)
            if prior is not None:
                if not isinstance(prior, (int, float)) or not prior > 0:
                    raise ParameterError(f"{source}: prior_std of {key!r} must be a positive number")
                p.prior_std = float(prior)
            if p.minimum is not None and p.maximum is not None and p.minimum > p.maximum:
                raise ParameterError(f"{source}: parameter {key!r} has min {p.minimum:g} above max {p.maximum:g}")
            lo, hi = p.minimum, p.maximum
            if (lo is not None and p.value < lo) or (hi is not None and p.value > hi):
                raise ParameterError(f"{source}: parameter {key!r} = {p.value:g} lies outside its bounds "
                                     f"[{'-inf' if lo is None else f'{lo:g}'}, {'inf' if hi is None else f'{hi:g}'}] "
                                     f"{p.unit}")
        return params

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of every parameter (±inf where there is none)."""
        return (np.array([-math.inf if p.minimum is None else p.minimum for p in self._items]),
                np.array([math.inf if p.maximum is None else p.maximum for p in self._items]))

    def to_document(self) -> dict[str, Any]:
        """START.json form."""
        return {"model": self.model_name, "parameters": self.as_dict()}


def load_document(path: str | Path) -> tuple[Any, str]:
    """A parameter file's JSON document and the name to quote it by; ``FILE#LABEL`` gives
    the document of experiment LABEL of a --per-experiment result."""
    path = Path(path)
    label = None
    if not path.exists() and "#" in path.name:
        name, _, label = path.name.rpartition("#")
        path = path.with_name(name)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ParameterError(f"{path}: parameter file not found") from None
    except OSError as exc:
        raise ParameterError(f"{path}: cannot read the parameter file ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ParameterError(f"{path}: not a text (UTF-8) file") from None
    except json.JSONDecodeError as exc:
        raise ParameterError(f"{path}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    if label is None:
        return doc, str(path)
    return _experiment_document(doc, label, str(path)), f"{path}#{label}"


def _experiment_document(doc: Any, label: str, source: str) -> dict[str, Any]:
    """The RESULT.json document of one experiment of a --per-experiment result."""
    fits = doc.get("per_experiment") if isinstance(doc, dict) else None
    if not isinstance(fits, dict):
        raise ParameterError(f"{source}#{label}: {source} is not a --per-experiment result (no 'per_experiment')")
    if label not in fits or not isinstance(fits[label], dict):
        raise ParameterError(f"{source}#{label}: no experiment {label!r} in it (experiments: {', '.join(fits)})")
    return dict(fits[label])


def _set_bound(p: Parameter, bound: str, raw: Any, source: str) -> None:
    """A START file's min or max for p: it may narrow the declared physical range, not widen it."""
    if not isinstance(raw, (int, float)) or isinstance(raw, bool) or not math.isfinite(raw):
        raise ParameterError(f"{source}: {bound} of {p.name!r} must be a finite number, got {raw!r}")
    lo, hi = p.physical
    if bound == "min":
        if lo is not None and raw < lo:
            raise ParameterError(f"{source}: min {raw:g} of {p.name!r} is below its physical minimum {lo:g} {p.unit} "
                                 f"(the model's declaration)")
        p.minimum = float(raw)
    else:
        if hi is not None and raw > hi:
            raise ParameterError(f"{source}: max {raw:g} of {p.name!r} is above its physical maximum {hi:g} {p.unit} "
                                 f"(the model's declaration)")
        p.maximum = float(raw)
