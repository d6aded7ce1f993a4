"""Spectroradiometer measurement sessions: a TOML manifest plus one spectrum file per reading.

The format is documented in ``docs/measurements.md``. This module holds what a loaded session
says: the readings (measured spots: instrument position and aim in world metres, full field
angle in degrees, repeats as (M, L) radiance in W·sr⁻¹·m⁻²·nm⁻¹ on the scene's wavelength grid,
dark subtracted), the white standard, the objects' measured reflectance and what to fit, the
noise model, and the names of the reflection-model parameters and reading kinds. Loading and
validation are in :func:`~spectral_fit.io.load_session`, writing in
:func:`~spectral_fit.io.write_session`.

This module is plain NumPy (the data layer).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from .._runtime.errors import InputError
from ._image_reading import ImageReading
from ._manifest import _line_of
from ._noise import NoiseModel
from ._scene import Scene

__all__ = [
    "PARAMETERS",
    "DEFAULT_FREE",
    "PHYSICAL_LOWER",
    "KINDS",
    "DATA_KINDS",
    "Reading",
    "WhiteStandard",
    "ObjectMeasurement",
    "Session",
]

#: Reflection-model parameters per object (docs/conventions.md), in this order everywhere.
PARAMETERS = ("alpha", "beta", "chi", "mu", "n", "gamma")
DEFAULT_FREE = ("alpha", "beta", "chi", "mu", "n")
#: each parameter's physical lower limit and whether that end is open (none has an upper one)
PHYSICAL_LOWER = {"alpha": (0.0, True), "beta": (0.0, True), "chi": (0.0, False),
                  "mu": (0.0, True), "n": (1.0, True), "gamma": (0.0, False)}
KINDS = ("object", "interreflection")
#: the kinds of data a fit compares: the spot kinds and camera photographs ("image")
DATA_KINDS = KINDS + ("image",)
CALIBRATION_MODES = ("white", "global", "none")


@dataclasses.dataclass(frozen=True)
class Reading:
    """One measured spot (possibly repeated).

    Attributes:
        id: unique name.
        object: the object the spot lies on (a name of the scene config).
        kind: "object" (object colour) or "interreflection".
        files: the spectrum files (repeats).
        repeats: (M, L) radiance of each repeat on the scene grid, W·sr⁻¹·m⁻²·nm⁻¹, dark
            subtracted.
        position: (3,) instrument entrance pupil, world metres.
        aim: (3,) the point aimed at, world metres.
        field_angle_deg: full angle of the measuring field.
        distance_m: measured distance to the spot (checked against the geometry) or None.
        line: line of the ``[[readings]]`` header in the manifest.
        index: position in the manifest's list.
    """

    id: str
    object: str
    kind: str
    files: tuple[Path, ...]
    repeats: np.ndarray
    position: np.ndarray
    aim: np.ndarray
    field_angle_deg: float
    distance_m: float | None
    line: int | None
    index: int

    @property
    def mean(self) -> np.ndarray:
        """(L,) mean radiance over the repeats."""
        return self.repeats.mean(axis=0)

    @property
    def field(self) -> str:
        return f"readings[{self.index}]"


@dataclasses.dataclass(frozen=True)
class WhiteStandard:
    """A diffuse reflectance standard read at the objects' position (calibration)."""

    reflectance: np.ndarray  # (L,)
    position: np.ndarray  # (3,)
    normal: np.ndarray  # (3,) unit
    instrument_position: np.ndarray  # (3,)
    repeats: np.ndarray  # (M, L) radiance, dark subtracted
    files: tuple[Path, ...]

    @property
    def mean(self) -> np.ndarray:
        return self.repeats.mean(axis=0)


@dataclasses.dataclass(frozen=True)
class ObjectMeasurement:
    """What the session says about one object: its measured reflectance and what to fit."""

    name: str
    reflectance: np.ndarray | None  # (L,) spectrophotometer S(λ), or None: the config's
    geometry: str  # "SCE" | "SCI"
    free: tuple[str, ...]
    start: dict[str, float]
    #: {parameter: (lower, upper)} limits of the fit (None: the physical limit)
    bounds: dict[str, tuple[float | None, float | None]] = dataclasses.field(
        default_factory=dict)
    #: {parameter: (mean, sigma)} Gaussian priors (e.g. n from a datasheet)
    prior: dict[str, tuple[float, float]] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class Session:
    """A loaded, validated measurement session (see ``docs/measurements.md``)."""

    path: Path  # the manifest
    scene_path: Path | None
    scene: Scene | None  # the scene the session's objects name
    wavelengths: np.ndarray
    units: str
    instrument: str
    calibration: str  # "white" | "global" | "none"
    bandwidth_nm: float  # instrument band-pass FWHM (0: none)
    reference: str | None  # "global" mode: object whose alpha is held fixed
    white: WhiteStandard | None
    dark: np.ndarray | None  # (L,) mean dark reading subtracted from everything
    noise: NoiseModel
    objects: dict[str, ObjectMeasurement]
    readings: tuple[Reading, ...]
    lines: dict[str, int] = dataclasses.field(repr=False, default_factory=dict)
    #: the model's own error per reading kind, relative to each reading and added to its σ in
    #: quadrature: {kind: fraction, or "auto" (the fit estimates it from its residuals)};
    #: kinds not named: 0
    model_error: dict[str, float | str] = dataclasses.field(default_factory=dict)
    #: the part of the model's error shared by all bands of a reading, 1σ as fractions of the
    #: reading, per kind: a level (``[model_error.level]``) and a tilt from −1 at the first
    #: band to +1 at the last (``[model_error.tilt]``); the fit weights each reading by the
    #: covariance diag(σ²) + ℓ² L Lᵀ + t² (L∘x)(L∘x)ᵀ (generalised least squares); kinds
    #: not named: 0
    level_error: dict[str, float] = dataclasses.field(default_factory=dict)
    tilt_error: dict[str, float] = dataclasses.field(default_factory=dict)
    #: camera photographs used as readings (``[[images]]``)
    images: tuple[ImageReading, ...] = ()

    def line_of(self, field: str) -> int | None:
        """Manifest line of a dotted field (``readings[2].aim``), or of its table."""
        return _line_of(self.lines, field)

    def error(self, field: str, message: str) -> InputError:
        return InputError(message, path=self.path, field=field, line=self.line_of(field))

    @property
    def object_names(self) -> tuple[str, ...]:
        """The scene's objects in config order."""
        return tuple(o.name for o in self.scene.objects)

    def replace(self, **changes: Any) -> Session:
        return dataclasses.replace(self, **changes)

    def select(self, kinds: tuple[str, ...]) -> Session:
        """The same session with only the readings of the given kinds."""
        return self.replace(readings=tuple(r for r in self.readings if r.kind in kinds))
