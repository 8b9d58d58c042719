"""Declared models: equations written once, every derivative derived from them.

A model is a subclass of :class:`ModelDeclaration`.  It names its states, the dataset
columns it takes as inputs and offers as outputs (with the unit conversion to SI), its
parameters, and writes its residual equations ``g(x, x', x'', u, θ) = 0`` and output
equations ``ŷ(x, x', x'', u, θ)`` with sympy symbols.  :func:`compile_model` derives the
Jacobians with respect to the states, their time derivatives and the parameters,
prints them as plain numpy code and caches that code on disk, so that a later process
loads the generated module without importing sympy at all.
"""

from __future__ import annotations

import hashlib
import importlib.util
import inspect
import logging
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any, ClassVar

import numpy as np

from identify.differentiation import periodic_derivative
from identify.errors import InputError
from identify.files import atomic_write_bytes

GENERATOR_VERSION = "7"
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ParameterSpec:
    """A model parameter as declared: stable name, descriptive alias, SI unit, nominal
    value, and the physical range the estimator keeps it in (``minimum=0.0`` for a mass
    or a damping coefficient; None: unbounded)."""

    name: str
    alias: str
    unit: str
    nominal: float
    description: str = ""
    minimum: float | None = None
    maximum: float | None = None


@dataclass(frozen=True)
class Channel:
    """A dataset column and its conversion to SI: ``si = (column + offset) * scale``."""

    column: str
    unit: str
    scale: float = 1.0
    offset: float = 0.0

    def to_si(self, values: np.ndarray) -> np.ndarray:
        return (np.asarray(values, dtype=float) + self.offset) * self.scale

    def from_si(self, values: np.ndarray) -> np.ndarray:
        return np.asarray(values, dtype=float) / self.scale - self.offset


@dataclass(frozen=True)
class State:
    """A state variable; ``scale`` is its typical size in SI, used for convergence tests."""

    name: str
    unit: str
    scale: float


class ModelDeclaration:
    """Base class of a declared model.  Subclasses set the class attributes and write
    :meth:`residuals` and :meth:`output_equations` with the sympy symbols they receive."""

    name: ClassVar[str]
    description: ClassVar[str] = ""
    states: ClassVar[tuple[State, ...]]
    inputs: ClassVar[dict[str, Channel]]  # input symbol -> dataset column
    outputs: ClassVar[dict[str, Channel]]  # output name (= column) -> channel
    default_outputs: ClassVar[tuple[str, ...]]  # outputs fitted unless told otherwise
    parameters: ClassVar[tuple[ParameterSpec, ...]]

    def residuals(self, s: SimpleNamespace) -> list[Any]:
        """Residual equations g = 0, one per state.  ``s.x``, ``s.x_t``, ``s.x_tt`` are a
        state and its first and second time derivatives; inputs and parameters by name
        (and parameters also by alias)."""
        raise NotImplementedError

    def output_equations(self, s: SimpleNamespace) -> dict[str, Any]:
        """Output equations, keyed by output name (the dataset column)."""
        raise NotImplementedError

    def static_guess(self, theta: dict[str, float]) -> dict[str, float]:
        """Starting point of the static-equilibrium Newton solve (default: all zero)."""
        return {}


class ModelError(InputError):
    """A model declaration that cannot be compiled or loaded."""


# --------------------------------------------------------------------------------------
# Compiled model: the numeric face of a declaration.


@dataclass
class CompiledModel:
    """Numeric functions generated from a declaration.

    Array conventions: states ``X``, ``DX``, ``DDX`` have shape ``(n_states, n)`` (time
    derivatives, not phase derivatives), inputs ``U`` ``(n_inputs, n)``, parameters
    ``P`` ``(n_params,)``.  Jacobian blocks come back as ``(n_eq, n_states, n)``,
    parameter derivatives as ``(n_eq, n_params, n)`` and input derivatives as
    ``(n_eq, n_inputs, n)``; outputs likewise with ``n_out``.
    """

    declaration: ModelDeclaration
    module: ModuleType
    source_path: Path
    version: str  # digest of the declaration's source and the generator: changes whenever the equations may

    def __post_init__(self) -> None:
        d = self.declaration
        self.name: str = d.name
        self.state_names: tuple[str, ...] = tuple(s.name for s in d.states)
        self.state_scales = np.array([s.scale for s in d.states])
        self.input_names: tuple[str, ...] = tuple(d.inputs)
        self.output_names: tuple[str, ...] = tuple(self.module.OUTPUT_NAMES)
        self.parameter_specs: tuple[ParameterSpec, ...] = tuple(d.parameters)
        self.parameter_names: tuple[str, ...] = tuple(p.name for p in d.parameters)
        self.orders: tuple[int, ...] = tuple(self.module.ORDERS)
        # (input index, order) of each input derivative the equations use: rows of U after the inputs
        self.input_derivatives: tuple[tuple[int, int], ...] = tuple(
            (int(j), int(o)) for j, o in self.module.INPUT_DERIVATIVES)
        # Residuals with kinks or jumps (|x|, sign, max, ...): their periodic solutions
        # converge only at second order in the grid step, whatever the scheme.
        self.nonsmooth: bool = bool(self.module.NONSMOOTH)
        m = self.module
        self.residual: Callable[..., np.ndarray] = m.residual
        self.residual_jacobian: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]] = m.residual_jacobian
        self.residual_dtheta: Callable[..., np.ndarray] = m.residual_dtheta
        self.residual_dinput: Callable[..., np.ndarray] = m.residual_dinput
        self.output: Callable[..., np.ndarray] = m.output
        self.output_jacobian: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]] = m.output_jacobian
        self.output_dtheta: Callable[..., np.ndarray] = m.output_dtheta
        self.output_dinput: Callable[..., np.ndarray] = m.output_dinput

    @property
    def n_states(self) -> int:
        return len(self.state_names)

    def expand_inputs(self, inputs: np.ndarray, frequency_hz: float, axis: int = -1) -> np.ndarray:
        """The inputs (n_inputs, …) of one period on its grid with the input derivatives
        the equations use appended as rows (computed spectrally along ``axis``, the
        phase grid): what every generated function takes as U.  Linear, so it maps an
        input perturbation (noise draws) the same way."""
        if not self.input_derivatives:
            return inputs
        rows = [periodic_derivative(inputs[j], frequency_hz, order, axis=axis if axis < 0 else axis - 1)
                for j, order in self.input_derivatives]
        return np.concatenate([inputs, np.stack(rows)], axis=0)

    def collapse_inputs(self, adjoint: np.ndarray, frequency_hz: float, axis: int = -1) -> np.ndarray:
        """The transpose of :meth:`expand_inputs`: weights on the expanded rows
        (n_inputs + derivatives, …) back onto the inputs' own rows."""
        if not self.input_derivatives:
            return adjoint
        n_in = len(self.input_names)
        out = adjoint[:n_in].copy()
        for r, (j, order) in enumerate(self.input_derivatives):
            out[j] += periodic_derivative(adjoint[n_in + r], frequency_hz, order,
                                          axis=axis if axis < 0 else axis - 1, transposed=True)
        return out

    def parameter_index(self, name_or_alias: str) -> int:
        for i, p in enumerate(self.parameter_specs):
            if name_or_alias in (p.name, p.alias):
                return i
        known = ", ".join(f"{p.name} ({p.alias})" for p in self.parameter_specs)
        raise ModelError(f"model {self.name!r} has no parameter {name_or_alias!r}; it has {known}")

    def output_index(self, name: str) -> int:
        try:
            return self.output_names.index(name)
        except ValueError:
            raise ModelError(
                f"model {self.name!r} has no output {name!r}; it has {', '.join(self.output_names)}"
            ) from None

    def nominal_vector(self) -> np.ndarray:
        return np.array([p.nominal for p in self.parameter_specs], dtype=float)

    def static_guess(self, theta: np.ndarray) -> np.ndarray:
        guess = self.declaration.static_guess(dict(zip(self.parameter_names, theta, strict=True)))
        return np.array([guess.get(s, 0.0) for s in self.state_names], dtype=float)


# --------------------------------------------------------------------------------------
# Code generation.


def _symbols(decl: ModelDeclaration):
    import sympy as sp

    s = SimpleNamespace()
    xs, dxs, ddxs, us, dus, ps = [], [], [], [], [], []
    for st in decl.states:
        x, dx, ddx = sp.symbols(f"{st.name} {st.name}_t {st.name}_tt", real=True)
        setattr(s, st.name, x)
        setattr(s, f"{st.name}_t", dx)
        setattr(s, f"{st.name}_tt", ddx)
        xs.append(x)
        dxs.append(dx)
        ddxs.append(ddx)
    for name in decl.inputs:
        u = sp.Symbol(name, real=True)
        setattr(s, name, u)
        us.append(u)
    for name in decl.inputs:  # an input's time derivatives: rows after the inputs where used
        for suffix in ("_t", "_tt"):
            d = sp.Symbol(f"{name}{suffix}", real=True)
            setattr(s, f"{name}{suffix}", d)
            dus.append(d)
    for p in decl.parameters:
        sym = sp.Symbol(p.name, real=True)
        setattr(s, p.name, sym)
        if p.alias and p.alias != p.name:
            setattr(s, p.alias, sym)
        ps.append(sym)
    return s, xs, dxs, ddxs, us, dus, ps


def _function_source(name: str, entries: list[tuple[tuple[int, ...], Any]], shapes: list[tuple[int, ...]],
                     symbols, printer) -> str:
    """Source of ``def name(X, DX, DDX, U, P)`` that fills arrays of the given shapes
    (leading dims; the time axis is appended) from ``entries`` ((array, *index), expr)."""
    import sympy as sp

    xs, dxs, ddxs, us, ps = symbols
    lines = [f"def {name}(X, DX, DDX, U, P):"]
    lines += [f"    {x} = X[{i}]" for i, x in enumerate(xs)]
    lines += [f"    {x} = DX[{i}]" for i, x in enumerate(dxs)]
    lines += [f"    {x} = DDX[{i}]" for i, x in enumerate(ddxs)]
    lines += [f"    {u} = U[{i}]" for i, u in enumerate(us)]
    lines += [f"    {p} = P[{i}]" for i, p in enumerate(ps)]
    lines.append("    _tail = np.shape(X)[1:]")
    for k, shp in enumerate(shapes):
        lines.append(f"    _o{k} = np.zeros({shp!r} + _tail)")
    exprs = [e for _, e in entries]
    repl, reduced = sp.cse(exprs, symbols=sp.numbered_symbols("_c"), optimizations="basic")
    for sym, e in repl:
        lines.append(f"    {sym} = {printer.doprint(e)}")
    for (idx, _), e in zip(entries, reduced, strict=True):
        arr, *pos = idx
        lines.append(f"    _o{arr}[{', '.join(map(str, pos))}] = {printer.doprint(e)}")
    outs = ", ".join(f"_o{k}" for k in range(len(shapes)))
    lines.append(f"    return {outs}")
    return "\n".join(lines) + "\n"


def generate_source(decl: ModelDeclaration) -> str:
    """Derive all Jacobians of a declaration symbolically and print them as numpy code."""
    import sympy as sp
    from sympy.printing.numpy import NumPyPrinter

    if not decl.states:
        raise ModelError(f"model {decl.name!r} declares no state: identify solves periodic equations for states; "
                         f"a force that is a function of the imposed motion alone is a regression, not such a model")
    s, xs, dxs, ddxs, us, dus, ps = _symbols(decl)
    g = [sp.sympify(e) for e in decl.residuals(s)]
    if len(g) != len(xs):
        raise ModelError(f"model {decl.name!r}: {len(g)} residual equations for {len(xs)} states")
    h_map = decl.output_equations(s)
    out_names = list(h_map)
    h = [sp.sympify(h_map[k]) for k in out_names]
    missing = set(out_names) ^ set(decl.outputs)
    if missing:
        raise ModelError(f"model {decl.name!r}: outputs and output equations differ in {sorted(missing)}")
    allowed = set(xs) | set(dxs) | set(ddxs) | set(us) | set(dus) | set(ps)
    for e in g + h:
        stray = e.free_symbols - allowed
        if stray:
            raise ModelError(f"model {decl.name!r}: unknown symbols {sorted(map(str, stray))} in {e}")
    # Input derivatives the equations use become extra input rows, computed from the
    # folded input on the periodic grid (CompiledModel.expand_inputs).
    every = set().union(*(e.free_symbols for e in g + h))
    derived = [(j, order) for j in range(len(us)) for order in (1, 2) if dus[2 * j + order - 1] in every]
    us = us + [dus[2 * j + order - 1] for j, order in derived]
    syms = (xs, dxs, ddxs, us, ps)

    kinks = (sp.Abs, sp.sign, sp.Heaviside, sp.Max, sp.Min, sp.Piecewise, sp.floor, sp.ceiling)
    used = set().union(*(e.free_symbols for e in g))
    orders = [2 if ddx in used else 1 if dx in used else 0 for dx, ddx in zip(dxs, ddxs, strict=True)]

    class _Printer(NumPyPrinter):
        # np.sign(0) = 0 is the right derivative of x|x| at 0; keep numpy's names short.
        def _print_sign(self, expr):  # pragma: no cover - printer hook
            return f"np.sign({self._print(expr.args[0])})"

        # The derivative of a jump (sign, Heaviside) is zero wherever it exists: the
        # generalised Jacobian of semismooth Newton, which needs no point mass.
        def _print_DiracDelta(self, expr):  # pragma: no cover - printer hook
            return "0"

    printer = _Printer({"fully_qualified_modules": True, "inline": True, "allow_unknown_functions": True})
    neq, ns, nout, npar = len(g), len(xs), len(h), len(ps)

    def jac_entries(exprs, wrt_groups):
        entries = []
        for i, e in enumerate(exprs):
            for a, group in enumerate(wrt_groups):
                for j, v in enumerate(group):
                    d = sp.diff(e, v)
                    if d != 0:
                        entries.append(((a, i, j), d))
        return entries

    parts = [
        "# Generated by identify.model from the declaration of model "
        f"{decl.name!r}; do not edit.\n",
        "import functools\nimport numpy\nimport numpy as np\n",
        f"ORDERS = {orders!r}\n",
        f"NONSMOOTH = {any(e.has(*kinks) for e in g)!r}\n",
        f"OUTPUT_NAMES = {out_names!r}\n",
        f"INPUT_DERIVATIVES = {derived!r}\n",
        _function_source("residual", [((0, i), e) for i, e in enumerate(g)], [(neq,)], syms, printer),
        _function_source("residual_jacobian", jac_entries(g, [xs, dxs, ddxs]), [(neq, ns)] * 3, syms, printer),
        _function_source("residual_dtheta", jac_entries(g, [ps]), [(neq, npar)], syms, printer),
        _function_source("residual_dinput", jac_entries(g, [us]), [(neq, len(us))], syms, printer),
        _function_source("output", [((0, i), e) for i, e in enumerate(h)], [(nout,)], syms, printer),
        _function_source("output_jacobian", jac_entries(h, [xs, dxs, ddxs]), [(nout, ns)] * 3, syms, printer),
        _function_source("output_dtheta", jac_entries(h, [ps]), [(nout, npar)], syms, printer),
        _function_source("output_dinput", jac_entries(h, [us]), [(nout, len(us))], syms, printer),
    ]
    return "\n\n".join(parts)


def cache_dir() -> Path:
    """Where generated model code is kept (``IDENTIFY_CACHE_DIR`` overrides)."""
    env = os.environ.get("IDENTIFY_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or (Path.home() / ".cache")
    return Path(base) / "damper-rig" / "models"


def _declaration_key(cls: type) -> str:
    try:
        text = Path(inspect.getsourcefile(cls) or "").read_text()
    except (OSError, TypeError):
        text = repr(sorted(vars(cls).items(), key=lambda kv: kv[0]))
    h = hashlib.sha256()
    for part in (GENERATOR_VERSION, cls.__module__, cls.__qualname__, text):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:20]


def _load_module(path: Path, modname: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(modname, path)
    assert spec and spec.loader
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_COMPILED: dict[type, CompiledModel] = {}


def compile_model(cls: type[ModelDeclaration]) -> CompiledModel:
    """Compiled form of a declaration, generating and caching its code on first use."""
    if cls in _COMPILED:
        return _COMPILED[cls]
    decl = cls()
    key = _declaration_key(cls)
    directory = cache_dir()
    path = directory / f"{decl.name}_{key}.py"
    modname = f"_identify_generated_{decl.name}_{key}"
    module = None
    if path.exists():
        try:
            module = _load_module(path, modname)
        except Exception as exc:  # a truncated or stale cache file: regenerate below
            log.info("model %s: the cached code %s cannot be loaded (%s: %s); generated again",
                     decl.name, path, type(exc).__name__, exc)
            module = None
    if module is None:
        src = generate_source(decl)
        try:
            atomic_write_bytes(path, src.encode())
            module = _load_module(path, modname)
        except OSError as exc:
            # Read-only home: keep the generated code in memory for this process.
            log.info("model %s: the generated code cannot be cached in %s (%s); kept in memory",
                     decl.name, directory, exc.strerror or exc)
            module = ModuleType(modname)
            exec(compile(src, f"<generated {decl.name}>", "exec"), module.__dict__)
    sys.modules.setdefault(modname, module)
    compiled = CompiledModel(decl, module, path, key)
    _COMPILED[cls] = compiled
    return compiled


# --------------------------------------------------------------------------------------
# Registry of built-in models and loading of user models.

_BUILTIN = {
    "1dof": ("identify.models.damper", "Damper1Dof"),
    "2dof": ("identify.models.damper", "Damper2Dof"),
    "duffing": ("identify.models.duffing", "Duffing"),
    "bouc-wen": ("identify.models.bouc_wen", "BoucWen"),
}


# What an identification of a built-in damper model estimates unless told otherwise (the
# rest comes from drawings and gas data): one definition for every command, window and script.
DEFAULT_ESTIMATE = {"1dof": ("theta5", "theta6", "theta7"), "2dof": ("theta4", "theta6", "theta16")}


def builtin_models() -> list[str]:
    return list(_BUILTIN)


def load_model(spec: str) -> CompiledModel:
    """A model by built-in name (``1dof``, ``2dof``, ``duffing``, ``bouc-wen``) or ``path/file.py:ClassName``."""
    if spec in _BUILTIN:
        modname, clsname = _BUILTIN[spec]
        cls = getattr(importlib.import_module(modname), clsname)
        return compile_model(cls)
    if ":" not in spec:
        raise ModelError(
            f"unknown model {spec!r}: use one of {', '.join(_BUILTIN)} or path/to/file.py:ClassName"
        )
    file, _, clsname = spec.rpartition(":")
    path = Path(file)
    if not path.is_file():
        raise ModelError(f"model file {file!r} not found")
    modname = f"_identify_user_{path.stem}"
    try:
        spec_ = importlib.util.spec_from_file_location(modname, path.resolve())
        assert spec_ and spec_.loader
        module = importlib.util.module_from_spec(spec_)
        # Registered before running so that inspect finds the source for the cache key.
        sys.modules[modname] = module
        spec_.loader.exec_module(module)
    except Exception as exc:
        sys.modules.pop(modname, None)
        raise ModelError(f"model file {file}: cannot be loaded: {exc}") from exc
    cls = getattr(module, clsname, None)
    if not (isinstance(cls, type) and issubclass(cls, ModelDeclaration)):
        raise ModelError(f"model file {file}: no ModelDeclaration subclass named {clsname!r}")
    return compile_model(cls)


__all__ = [
    "Channel",
    "CompiledModel",
    "ModelDeclaration",
    "ModelError",
    "ParameterSpec",
    "State",
    "builtin_models",
    "cache_dir",
    "compile_model",
    "load_model",
]
