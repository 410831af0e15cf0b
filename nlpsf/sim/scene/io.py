"""Reading scenes: the presets of this package, JSON, files, and user input (CLI strings, the
REST API's ``scene`` object) turned into a :class:`~nlpsf.sim.scene.model.SceneModel`.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_number
from nlpsf.roman import seds

from .model import SED_NAMES, SceneModel, check_kernel
from .registry import MAX_IPC_ALPHA, REGISTRY, ROMAN_IPC_KERNEL

#: The IPC kernels ``ipc`` takes by name.
NAMED_IPC_KERNELS = {"roman": ROMAN_IPC_KERNEL}
#: Preset names a scene file may not use here, and where they live.
_ELSEWHERE = {"roman": "; the Roman default's scene is nlpsf.request.presets.preset_base('roman')"}


def preset(name: str) -> SceneModel:
    """A named scene of this module: "paper", the paper's idealised scene; "galsim-roman", GalSim's
    Roman constants (the registry's effects marked for it at their nominal values: jitter 0.014",
    diffusion 0.1 px, flat f_nu, GalSim's IPC), which the GalSim cross-checks use. The Roman
    default's scene ("roman") is ``nlpsf.request.presets``'s (``roman_default.preset_base``), which
    builds on this module."""
    galsim_values = {k: v for e in REGISTRY.values() if e.in_roman_preset for k, v in e.nominal.items()}
    presets = {"paper": SceneModel(name="paper"), "galsim-roman": SceneModel(name="galsim-roman", **galsim_values)}
    if name not in presets:
        hint = _ELSEWHERE.get(name, "")
        raise InputError("scene", f"unknown scene preset {name!r}; presets: {', '.join(PRESETS)}, or a JSON file{hint}")
    return presets[name]


#: This module's scene presets by name ("roman", the default's scene, is ``nlpsf.request.presets``'s).
PRESETS = ("paper", "galsim-roman")


def to_json(scene: SceneModel) -> str:
    data = asdict(scene)
    return json.dumps(data, indent=1)


def from_dict(data: dict) -> SceneModel:
    if not isinstance(data, dict):
        raise InputError("scene", "a scene must be a JSON object")
    known = {f.name for f in fields(SceneModel)}
    unknown = sorted(set(data) - known - {"effects_on"})
    if unknown:
        raise InputError("scene", f"unknown scene fields {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    values = {k: v for k, v in data.items() if k in known}
    for key in ("position", "nl_coefficients"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    if values.get("ipc") is not None:
        values["ipc"] = tuple(tuple(row) for row in values["ipc"])
    if values.get("sed_table") is not None:
        values["sed_table"] = tuple(tuple(col) for col in values["sed_table"])
    return SceneModel(**values)


def save(scene: SceneModel, path) -> None:
    Path(path).write_text(to_json(scene) + "\n")


def load(name_or_path: str) -> SceneModel:
    """A preset by name, or a scene saved as JSON."""
    if name_or_path in PRESETS:
        return preset(name_or_path)
    path = Path(name_or_path)
    if not path.is_file():
        raise InputError("scene", f"no preset or file named {name_or_path!r}; presets: {', '.join(PRESETS)}")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise InputError("scene", f"cannot read {name_or_path}: {error}") from None
    return from_dict(data)


def read_table(path: str, name: str, columns: int) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is refused below, by shape
            array = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as error:
        raise InputError(name, f"cannot read {path}: {error}") from None
    if columns and array.shape[1] != columns:
        raise InputError(name, f"{path} must have {columns} columns, has {array.shape[1]}")
    return array


def parse_ipc(text) -> tuple[tuple[tuple[float, ...], ...] | None, str | None]:
    """``roman`` | ``none`` | a nearest-neighbour alpha | a 3x3 file -> (kernel, label)."""
    if text is None:
        return None, None
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        text = repr(float(text))
    if not isinstance(text, str):
        raise InputError("ipc", f"must be roman, a coupling alpha or a 3x3 file, got {text!r}")
    lowered = text.strip().lower()
    if lowered in ("", "none", "off"):
        return None, None
    if lowered in NAMED_IPC_KERNELS:
        return NAMED_IPC_KERNELS[lowered], lowered
    try:
        alpha = float(lowered)
    except ValueError:
        array = read_table(text, "ipc", 0)
        if array.shape != (3, 3):
            raise InputError("ipc", f"{text} must hold a 3x3 kernel, got shape {array.shape}") from None
        return check_kernel(array), f"file:{Path(text).name}"
    alpha = check_number(alpha, "ipc", 0.0, MAX_IPC_ALPHA)
    kernel = ((0.0, alpha, 0.0), (alpha, 1.0 - 4 * alpha, alpha), (0.0, alpha, 0.0))
    return check_kernel(kernel), f"alpha={alpha:g}"


def parse_sed(text: str | None, units: str = "flambda") -> dict:
    """``flat`` | ``blackbody:TEFF`` | a vendored name (``k0v``) | a two-column file -> SceneModel fields."""
    if text is None:
        return {}
    if not isinstance(text, str):
        raise InputError("sed", f"must be flat, blackbody:TEFF, {SED_NAMES} or a file, got {text!r}")
    stripped = text.strip()
    if stripped == "flat" or stripped.startswith("blackbody:") or seds.is_named(stripped):
        return {"sed": stripped}
    if not Path(stripped).is_file():
        raise InputError("sed", f"unknown SED {text!r}: use flat, blackbody:TEFF, {SED_NAMES} or a two-column file (nm, flux)")
    array = read_table(stripped, "sed", 2)
    return {"sed": f"file:{Path(stripped).name}", "sed_table": (tuple(array[:, 0]), tuple(array[:, 1])), "sed_units": units}


def parse_position(text) -> tuple[float, float] | None:
    if text is None:
        return None
    if isinstance(text, str):
        parts = text.replace(" ", "").split(",")
        if len(parts) != 2:
            raise InputError("position", f"give X,Y in SCA pixels (1-{roman.SCA_PIXELS}), got {text!r}")
        try:
            return float(parts[0]), float(parts[1])
        except ValueError:
            raise InputError("position", f"give X,Y in SCA pixels, got {text!r}") from None
    return tuple(text)


def parse_coefficients(text) -> tuple[float, ...]:
    if text is None:
        return ()
    if isinstance(text, str):
        try:
            return tuple(float(v) for v in text.split(",") if v.strip())
        except ValueError:
            raise InputError("nl_coefficients", f"give comma-separated numbers, got {text!r}") from None
    return tuple(text)


def from_options(
    base: SceneModel | str | None = None,
    *,
    position=None,
    sed=None,
    sed_units: str = "flambda",
    jitter=None,
    charge_diffusion=None,
    ipc=None,
    ipc_order: str | None = None,
    nl_coefficients=None,
    bfe=None,
    background=None,
    n_wavelengths: int | None = None,
) -> SceneModel:
    """A scene from a preset/file (``base``) overridden by user strings, as the CLI and API give them.

    ``nl_coefficients`` here are (b3, b4, ...); callers that accept b2 first split it off as beta0.
    """
    scene = base if isinstance(base, SceneModel) else (load(base) if base else SceneModel())
    changes: dict = {}
    if position is not None:
        changes["position"] = parse_position(position)
    if sed is not None:
        changes.update({"sed": None, "sed_table": None} | parse_sed(sed, sed_units))
    if jitter is not None:
        changes["jitter_arcsec"] = jitter
    if charge_diffusion is not None:
        changes["charge_diffusion_px"] = charge_diffusion
    if ipc is not None:
        changes["ipc"], changes["ipc_label"] = parse_ipc(ipc)
    if ipc_order is not None:
        changes["ipc_order"] = ipc_order
    if nl_coefficients is not None:
        changes["nl_coefficients"] = parse_coefficients(nl_coefficients)
    if bfe is not None:
        changes["bfe_coefficient"] = bfe
    if background is not None:
        changes["background_e"] = background
    if n_wavelengths is not None:
        changes["n_wavelengths"] = n_wavelengths
    return moved_or_changed(scene, changes)


def from_request(fields_: dict | None, base: SceneModel | None = None) -> SceneModel:
    """A scene from the REST API's ``scene`` object (no files on a server: tables and kernels inline).

    Keys: ``preset`` (paper | roman), ``position`` [x, y], ``sed`` (flat | blackbody:TEFF | k0v),
    ``sed_table`` [[nm, flux], ...] with ``sed_units``, ``jitter``, ``charge_diffusion``, ``ipc``
    (roman | alpha | 3x3 rows), ``ipc_order``, ``nl_coefficients`` (b3, b4, ...), ``bfe``,
    ``background``, ``n_wavelengths``. Unset keys keep the preset's value. ``base``: the scene the
    keys change when the caller resolved the preset (``nlpsf.request.presets.preset_base``).
    """
    if not fields_:
        return base or SceneModel()
    data = {k: v for k, v in fields_.items() if v is not None}
    named = data.pop("preset", None)
    if base is None:
        base = preset(named) if named is not None else SceneModel()
    changes: dict = {}
    if "sed_table" in data:
        rows = data.pop("sed_table")
        if data.get("sed") not in (None,) and not str(data.get("sed", "")).startswith("file"):
            raise InputError("sed", "give either sed or sed_table, not both")
        data.pop("sed", None)
        try:
            columns = tuple(zip(*rows, strict=True))
        except (TypeError, ValueError):
            raise InputError("sed_table", "must be rows of [wavelength nm, flux]") from None
        if len(columns) != 2:
            raise InputError("sed_table", "must be rows of [wavelength nm, flux]")
        changes.update(sed="file:request", sed_table=columns, sed_units=data.pop("sed_units", "flambda"))
    if "ipc" in data:
        value = data.pop("ipc")
        if isinstance(value, (list, tuple)):
            changes["ipc"], changes["ipc_label"] = check_kernel(value), "kernel"
        elif isinstance(value, str) and value.strip().lower() not in (*NAMED_IPC_KERNELS, "none", "off"):
            raise InputError("ipc", f"must be roman, a coupling alpha or 3x3 rows, got {value!r}")
        else:
            changes["ipc"], changes["ipc_label"] = parse_ipc(value)
    if "sed" in data:
        sed = data.pop("sed")
        if isinstance(sed, str) and sed.strip() != "flat" and not sed.strip().startswith("blackbody:") and not seds.is_named(sed):
            raise InputError("sed", f"unknown SED {sed!r}: use flat, blackbody:TEFF, {SED_NAMES} or sed_table")
        changes.update(sed=sed, sed_table=None)
    renames = {
        "jitter": "jitter_arcsec",
        "charge_diffusion": "charge_diffusion_px",
        "bfe": "bfe_coefficient",
        "background": "background_e",
    }
    for key, value in data.items():
        if key == "sed_units":
            changes["sed_units"] = value
        elif key in ("position", "nl_coefficients"):
            changes[key] = tuple(value)
        elif key in ("ipc_order", "n_wavelengths"):
            changes[key] = value
        elif key in renames:
            changes[renames[key]] = value
        else:
            raise InputError("scene", f"unknown scene field {key!r}")
    return moved_or_changed(base, changes)


def moved_or_changed(base: SceneModel, changes: dict) -> SceneModel:
    """``base`` with ``changes``, as every builder of a scene applies them: another scene, unnamed,
    when an effect changes; the same named scene when only its position moves (a preset at a point
    of the field is still that preset, as ``replace(scene, position=...)`` keeps it for the SCA range
    and the over-field answers), so that it describes itself alike however the position was given.
    A field given at the value it already has (an API body's ``sed_units`` default) changes nothing."""
    if not changes:
        return base
    same = all(getattr(base, key) == value for key, value in changes.items() if key != "position")
    if same and "position" in changes:
        return base.at(changes["position"])  # only the position moves: it alone is checked again
    return replace(base, name=base.name if same else None, **changes)
