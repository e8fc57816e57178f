"""The model file: what ``ambfit identify --json`` and ``ambfit diagnose --json`` write for ``ambfit force``.

A force is only as good as the model it comes from, and a JSON file is easy to damage: a parameter renamed or
deleted, a gap typed in metres where micrometres belong, a negative variance, a file of another kind or of a
newer ambfit.  The writer marks every record (:func:`stamp`): ``schema`` (the layout, :data:`SCHEMA`),
``kind`` (which command wrote it) and ``ambfit_version``; its ``model_state`` records the bearing
description it was fitted with.  The reader (:func:`read`) checks everything the force will use and refuses
with a :class:`ModelFileError` naming the file, the JSON key and the value:

- the marker: another kind of file (a posterior, a rig's truth, several groups), a schema or a major version
  newer than this ambfit; a file without a version is read (with a warning) only if all else holds;
- the parameters: every name known (no renamed key), every value finite, the covariance square, symmetric,
  finite, with non-negative variances; each axis' gap and origin together, every effect parameter estimated
  or held (a missing one would silently take its default);
- the physics, judged against the bearing: a gap within :data:`GAP_FACTOR` of the drawn gap (a gap in metres
  or in micrometres where the other unit belongs is many decades off), an origin smaller than its gap, ``k``
  positive and within :data:`K_FACTOR` of the drawing's;
- the contract's ``params`` block, when present, has the contract's keys only and agrees with ``model_state``
  (an edit of one and not the other changes nothing the force uses, so it is refused rather than ignored).
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re

import numpy as np

from ambfit.estimation.units import CONTRACT_PARAMS, HEAD
from ambfit.physics.bearing import AXES, Bearing, BearingError, short_repr

SCHEMA = "ambfit.model.v1"
"""The layout of the records :func:`stamp` marks; a reader refuses a newer one (``ambfit.model.v2``, ...)."""

KINDS = ("identify", "diagnose")
"""Kinds of record that hold a fitted model."""

GAP_FACTOR = 10.0
"""A model's gap must lie within this factor of the drawn gap (either way); a unit mistake is decades off."""

K_FACTOR = 10.0
"""A model's ``k`` must lie within this factor of the drawing's (``Bearing.force_constant``): a unit mistake in
currents or loads is decades off (a merely implausible ``k`` was already judged by the fit)."""

_FOREIGN = {"bayes": "a posterior of ambfit sample (force needs the least-squares model of ambfit identify --json)",
            "closed_form": "a closed-form result (Eq. 5-7), which has no covariance (identify with least squares)"}


class ModelFileError(ValueError):
    """A model JSON that cannot be used for force measurement; the message names the file, key and value."""


def stamp(record: dict, kind: str) -> dict:
    """``record`` with the markers a reader checks first: ``schema``, ``kind`` and ``ambfit_version``."""
    from ambfit import __version__

    return {"schema": SCHEMA, "kind": kind, "ambfit_version": __version__} | record


@dataclasses.dataclass(frozen=True)
class ModelFile:
    """A checked model record: the chosen ``state`` (``model_state``), where it sits in the file (``key``), and
    the file's provenance; ``warnings`` say what was accepted with reservations (no version)."""

    state: dict
    key: str
    source: str
    kind: str
    schema: str | None
    version: str | None
    warnings: tuple = ()
    params: dict | None = None          # the contract's params block of an identify record (µm, N·m²/A²)

    def provenance(self) -> dict:
        """What a force output records of its model file."""
        return {"model_file": self.source, "model_kind": self.kind, "model_schema": self.schema,
                "model_ambfit_version": self.version, "model_key": self.key}


def _bad(source: str, key: str, value, reason: str) -> ModelFileError:
    return ModelFileError(f"{source}: {key} = {short_repr(value)}: {reason}")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _major_minor(version: str) -> tuple[int, int] | None:
    m = re.match(r"^(\d+)\.(\d+)", version)
    return (int(m.group(1)), int(m.group(2))) if m else None


def _marker(record, source: str) -> tuple[str, str | None, str | None, list[str]]:
    """The record's kind, schema and version, checked (a newer schema or major version is refused)."""
    from ambfit import __version__

    if not isinstance(record, dict):
        raise _bad(source, "(top level)", type(record).__name__, "not an ambfit identify/diagnose output (a JSON "
                   "object with model_state)")
    notes = []
    schema = record.get("schema")
    if schema is not None:
        m = re.fullmatch(r"ambfit\.model\.v(\d+)", str(schema))
        if m is None:
            raise _bad(source, "schema", schema, f"not an ambfit model file (this ambfit reads {SCHEMA})")
        if int(m.group(1)) > int(SCHEMA.rsplit("v", 1)[1]):
            raise _bad(source, "schema", schema, f"written by a newer ambfit (this one reads {SCHEMA}); upgrade "
                       "ambfit to read it")
    version = record.get("ambfit_version")
    if version is not None:
        theirs, ours = _major_minor(str(version)), _major_minor(__version__)
        if not isinstance(version, str) or theirs is None:
            raise _bad(source, "ambfit_version", version, "not a version number (e.g. '0.2.0')")
        if ours is not None and theirs[0] > ours[0]:
            raise _bad(source, "ambfit_version", version, f"written by a newer major version of ambfit than this "
                       f"one ({__version__}); upgrade ambfit to read it")
        if ours is not None and theirs > ours:
            notes.append(f"{source}: written by ambfit {version}, newer than this ambfit {__version__}; every "
                         "value was checked")
    kind = record.get("kind")
    if kind is None:
        kind = _infer_kind(record, source)
        if version is None:
            notes.append(f"{source}: no ambfit_version or kind (written before ambfit recorded them, or by hand); "
                         "every value was checked, so it is used")
    elif kind not in KINDS:
        raise _bad(source, "kind", kind, f"this file holds no fitted model for force (kinds with one: "
                   f"{', '.join(KINDS)})")
    if "groups" in record:
        groups = record["groups"]
        raise _bad(source, "groups", f"{len(groups)} groups" if isinstance(groups, (list, dict)) else groups,
                   "one fit per group; force needs one model (identify one file without --by and give its --json)")
    if kind == "identify" and _foreign(record.get("method", "least_squares")):
        raise _bad(source, "method", record["method"], _FOREIGN[record["method"]])
    return kind, None if schema is None else str(schema), version, notes


def _foreign(method) -> bool:
    """Whether ``method`` names a result that holds no model for force (any JSON value: a list is no method)."""
    return isinstance(method, str) and method in _FOREIGN


def _infer_kind(record: dict, source: str) -> str:
    if "groups" in record:
        return "identify"
    if "model_state" in record:
        return "identify"
    if "baseline_fit" in record:
        return "diagnose"
    method = record.get("method")
    if _foreign(method):
        raise _bad(source, "method", method, _FOREIGN[method])
    if "rig" in record or "truth" in record:
        raise _bad(source, "rig", record.get("rig"), "a virtual rig's truth, not a fitted model (fit the data "
                   "with ambfit identify --json)")
    keys = ", ".join(list(record)[:6]) or "none"
    raise _bad(source, "(top level)", f"keys: {keys}", "not an ambfit identify/diagnose output (it has no "
               "model_state)")


def read(record, source: str = "<json>", use: str | None = None) -> ModelFile:
    """The model ``state`` of an identify or diagnose record, with its marker checked (not yet its values:
    :func:`check`).  ``use`` picks a diagnose record's model (see :meth:`FittedModel.from_json`)."""
    keys = {"verdict": "verdict_fit", "discrepancy": "discrepancy_fit", "ideal": "baseline_fit"}
    if use is not None and use not in keys:
        raise ValueError(f"use must be one of {sorted(keys)}, got {use!r}")
    kind, schema, version, notes = _marker(record, source)
    key, state = "model_state", (record.get("model_state") if use is None else None)
    if state is None:
        order = [keys[use]] if use is not None else ["verdict_fit", "discrepancy_fit", "baseline_fit"]
        key = next((k for k in order if record.get(k)), None)
        fitted = record.get(key) if key is not None else {}
        if not isinstance(fitted, dict):
            raise _bad(source, key, fitted, "not a fitted model record (a JSON object with model_state)")
        state, key = fitted.get("model_state"), f"{key}.model_state"
        if state is None and use is not None:
            raise ModelFileError(f"{source}: no {use} model in this JSON (a diagnose JSON has 'verdict' only "
                                 "when the verdict names effects, 'discrepancy' only when it was fitted)")
    if state is None:
        raise ModelFileError(f"{source}: no fitted model in this JSON (write it with ambfit identify --json or "
                             "ambfit diagnose --json)")
    if not isinstance(state, dict):
        raise _bad(source, key, state, "not a model state (a JSON object with names, values and covariance)")
    return ModelFile(state=state, key=key, source=source, kind=kind, schema=schema, version=version,
                     warnings=tuple(notes), params=record.get("params", {}) if key == "model_state" else None)


def recorded_bearing(mf: ModelFile) -> Bearing | None:
    """The bearing description the model was fitted with, when the file records it."""
    d = mf.state.get("bearing_description")
    if d is None:
        return None
    if not isinstance(d, dict):
        raise _bad(mf.source, f"{mf.key}.bearing_description", d, "not a bearing description")
    try:
        return Bearing.from_dict(d, source=f"{mf.source}: {mf.key}.bearing_description")
    except BearingError as exc:
        raise ModelFileError(str(exc)) from None


def differing_key(a: Bearing, b: Bearing) -> str | None:
    """The first contract key whose value differs between two bearing descriptions (None when they agree to
    the rounding of a file)."""
    da, db = a.to_dict(), b.to_dict()
    for key in dict.fromkeys([*da, *db]):
        x, y = da.get(key), db.get(key)
        if isinstance(x, dict) or isinstance(y, dict):
            x, y = (None if v is None else [*v["B_T"], *v["H_A_per_m"]] for v in (x, y))
        if isinstance(x, list) and isinstance(y, list) and len(x) == len(y):
            if np.allclose(x, y, rtol=1e-9, atol=0.0):
                continue
        elif _number(x) and _number(y):
            if math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-15):
                continue
        elif x == y:
            continue
        return key
    return None


def check(mf: ModelFile, bearing: Bearing) -> None:
    """Refuse (:class:`ModelFileError`) a model state that ``ambfit force`` could not trust with ``bearing``."""
    from ambfit.physics.effects import effect_by_name

    s, src, at = mf.state, mf.source, mf.key
    for name in ("names", "values", "covariance"):
        if name not in s:
            raise _bad(src, at, f"keys: {', '.join(s)}", f"no '{name}' (a model state has names, values and "
                       "covariance)")
    names, values, cov = s["names"], s["values"], s["covariance"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names) or not names:
        raise _bad(src, f"{at}.names", names, "not a list of parameter names")
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise _bad(src, f"{at}.names", dup, "named twice")
    if not isinstance(values, list) or len(values) != len(names):
        raise _bad(src, f"{at}.values", values, f"not {len(names)} values, one per name")
    for j, v in enumerate(values):
        if not (_number(v) and math.isfinite(v)):
            raise _bad(src, f"{at}.values[{j}] ({names[j]})", v, "not a finite number")
    p = len(names)
    if not (isinstance(cov, list) and len(cov) == p and all(isinstance(r, list) and len(r) == p for r in cov)):
        raise _bad(src, f"{at}.covariance", cov, f"not a {p} x {p} matrix, one row and column per name")
    for i, row in enumerate(cov):
        for j, c in enumerate(row):
            if not (_number(c) and math.isfinite(c)):
                raise _bad(src, f"{at}.covariance[{i}][{j}]", c, "not a finite number")
    c = np.asarray(cov, dtype=float)
    for j in range(p):
        if c[j, j] < 0:
            raise _bad(src, f"{at}.covariance[{j}][{j}] ({names[j]})", float(c[j, j]), "a negative variance (its "
                       "standard error would be imaginary)")
    scale = np.sqrt(np.outer(np.diag(c), np.diag(c)))
    i, j = np.unravel_index(np.argmax(np.abs(c - c.T) - 1e-6 * scale), c.shape)
    if abs(c[i, j] - c[j, i]) > 1e-6 * scale[i, j] + 1e-300:
        raise _bad(src, f"{at}.covariance[{i}][{j}]", float(c[i, j]), f"differs from covariance[{j}][{i}] = "
                   f"{c[j, i]!r}: a covariance is symmetric")
    specs = s.get("effects", [])
    if not isinstance(specs, list):
        raise _bad(src, f"{at}.effects", specs, "not a list of effects")
    allowed = set(HEAD)
    fields = []
    for e, spec in enumerate(specs):
        key = f"{at}.effects[{e}]"
        if not isinstance(spec, dict) or not isinstance(spec.get("name"), str):
            raise _bad(src, key, spec, "not an effect record (a JSON object with its name)")
        try:
            effect = effect_by_name(spec["name"])
            for piece in spec.get("off", []):
                effect = effect.without(piece)
        except (ValueError, AttributeError, TypeError) as exc:     # (TypeError: "off" not a list of names)
            raise _bad(src, key, spec.get("name"), str(exc).split("\n")[0]) from None
        held = spec.get("held", {})
        if not isinstance(held, dict):
            raise _bad(src, f"{key}.held", held, "not a table of held parameters")
        for field, v in held.items():
            arr = np.asarray(v, dtype=object).ravel()
            if field not in type(effect).RANGES or not all(_number(x) and math.isfinite(x) for x in arr):
                raise _bad(src, f"{key}.held.{field}", v, f"not a held parameter of {spec['name']} (finite numbers; "
                           f"parameters: {', '.join(type(effect).RANGES)})")
        for field in type(effect).RANGES:
            shared = f"{spec['name']}.{field}"
            allowed |= {shared, *(f"{shared}[{ax}]" for ax in AXES)}
            fields.append((key, shared, field in held))
    for j, n in enumerate(names):
        if n not in allowed:
            near = difflib.get_close_matches(n, sorted(allowed), n=1, cutoff=0.6)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise _bad(src, f"{at}.names[{j}]", n, f"not a parameter of this model (known: {', '.join(HEAD)} and "
                       f"the effects' 'effect.parameter'){hint}")
    for key, shared, held in fields:
        if not (held or shared in names or all(f"{shared}[{ax}]" in names for ax in AXES)):
            per_axis = [f"{shared}[{ax}]" for ax in AXES if f"{shared}[{ax}]" in names]
            raise _bad(src, f"{at}.names", per_axis or shared, f"the effect parameter {shared} is neither estimated "
                       f"(for both axes) nor held ({key}.held): the force would use a default nobody fitted")
    _check_head(mf, dict(zip(names, values)), bearing, bool(specs))
    _check_params(mf, bearing, names, values, c)


def _check_head(mf: ModelFile, vals: dict, bearing: Bearing, effects: bool) -> None:
    from ambfit.estimation.plausibility import _decades, _k_cause

    src, at = mf.source, f"{mf.key}.values"
    nominal = bearing.nominal_gap
    for ax in AXES:
        g, x0 = vals.get(f"g_{ax}0"), vals.get(f"{ax}0")
        if (g is None) != (x0 is None) or (effects and g is None):
            missing = f"g_{ax}0" if g is None else f"{ax}0"
            raise _bad(src, f"{mf.key}.names", list(vals), f"no {missing!r}: the model needs the gap and origin "
                       f"of axis {ax}{' (its effects use both axes)' if effects else ''}")
        if g is not None:
            ratio = g / nominal
            if not 1.0 / GAP_FACTOR <= ratio <= GAP_FACTOR:
                n = _decades(ratio)
                cause = (f"{ratio:.3g} x the drawn gap {nominal * 1e6:.4g} µm; model_state holds metres (SI): "
                         + ("a gap in micrometres" if n == 6 else f"a unit 10^{n} off" if n else
                            "not a gap of this bearing (a damaged file, or a model of another --bearing)"))
                raise _bad(src, f"{at} (g_{ax}0)", g, cause)
            if not abs(x0) < g:
                raise _bad(src, f"{at} ({ax}0)", x0, f"an origin as large as the gap g_{ax}0 = {g!r} m: the rotor "
                           "would sit in the pole")
        k = vals.get(f"k_{ax}")
        if k is not None:
            factor = k / bearing.force_constant(1.0)
            if k <= 0:
                raise _bad(src, f"{at} (k_{ax})", k, "a force constant must be positive" + (
                    ": " + _k_cause(factor, bearing) if k < 0 else ""))
            if not 1.0 / K_FACTOR <= factor <= K_FACTOR:
                raise _bad(src, f"{at} (k_{ax})", k, f"{factor:.3g} x the drawing's k at lamination 1: "
                           + _k_cause(factor, bearing))


def _check_params(mf: ModelFile, bearing: Bearing, names, values, cov) -> None:
    """The contract's ``params`` block (µm, N·m²/A²) of an identify record against ``model_state``."""
    params = mf.params
    if params is None:
        return
    src = mf.source
    if not isinstance(params, dict):
        raise _bad(src, "params", params, "not the contract's parameter block")
    contract = {key: (name, f) for name, key, f in CONTRACT_PARAMS}
    std = np.sqrt(np.diag(cov))
    for key, entry in params.items():
        if key not in contract:
            near = difflib.get_close_matches(key, list(contract), n=1, cutoff=0.6)
            raise _bad(src, f"params.{key}", entry, "not a contract parameter (" + ", ".join(contract) + ")"
                       + (f"; did you mean {near[0]!r}?" if near else ""))
        if not isinstance(entry, dict):
            raise _bad(src, f"params.{key}", entry, "not a {value, std} record")
        for part in ("value", "std"):
            v = entry.get(part)
            if not (_number(v) and math.isfinite(v)) or (part == "std" and v < 0):
                raise _bad(src, f"params.{key}.{part}", v, "not a finite number" if part == "value" or v is None
                           or not _number(v) or not math.isfinite(v) else "a negative standard error")
        name, f = contract[key]
        if key.startswith("g_"):
            ratio = entry["value"] * 1e-6 / bearing.nominal_gap
            if not 1.0 / GAP_FACTOR <= ratio <= GAP_FACTOR:
                from ambfit.estimation.plausibility import _decades

                n = _decades(ratio)
                raise _bad(src, f"params.{key}.value", entry["value"], f"{ratio:.3g} x the drawn gap: "
                           + ("likely metres given for µm" if n == -6 else f"a unit 10^{n} off" if n
                              else "not a gap of this bearing in µm"))
        if name not in names:
            raise _bad(src, f"params.{key}", entry, f"{name} is not in {mf.key}.names: the file was edited")
        j = names.index(name)
        if not (math.isclose(entry["value"], values[j] * f, rel_tol=1e-9, abs_tol=1e-12 * f)
                and math.isclose(entry["std"], std[j] * f, rel_tol=1e-6, abs_tol=1e-12 * f)):
            raise _bad(src, f"params.{key}", entry, f"disagrees with {mf.key} ({name} = {values[j] * f:.6g} ± "
                       f"{std[j] * f:.3g}): the file was edited; the force uses {mf.key}")



def unfitted_k(mf: ModelFile, axes, record: dict) -> list[str]:
    """The axes among ``axes`` whose ``k`` the model lacks because its fit had no known load there (force cannot
    be measured on them).  A missing gap or origin of an asked axis, or a ``k`` that the record says was
    identified but that ``model_state`` lacks, is refused (:class:`ModelFileError`)."""
    names = mf.state["names"]
    claimed = record.get("k_identified") if isinstance(record.get("k_identified"), dict) else {}
    out = []
    for ax in sorted(set(axes)):
        for n in (f"g_{ax}0", f"{ax}0"):
            if n not in names:
                raise _bad(mf.source, f"{mf.key}.names", names, f"no {n!r}: the readings on axis {ax} need it (a "
                           f"model fitted on axis {ax} has it)")
        if f"k_{ax}" not in names:
            key = dict((name, key) for name, key, _ in CONTRACT_PARAMS)[f"k_{ax}"]
            if claimed.get(ax) or (mf.params and key in mf.params):
                raise _bad(mf.source, f"{mf.key}.names", names, f"no 'k_{ax}', while the record says k_{ax} was "
                           "identified: the file was edited")
            out.append(ax)
    return out
