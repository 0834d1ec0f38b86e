"""Drive profile: motor nameplate, sampling and transmission geometry (CONTRACT section 4).

A profile is a small TOML file; every key is checked, unknown keys are an error that names the
key path, and the values land in frozen dataclasses.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, dataclass, fields
from pathlib import Path

from agent.errors import InputError, read_toml


@dataclass(frozen=True)
class Motor:
    """Nameplate of the driving PMSM (paper Table 2)."""

    pole_pairs: int
    rated_power_w: float
    rated_torque_nm: float
    rated_speed_rpm: float
    rated_voltage_v: float | None = None  #: line-to-line rms, optional
    rated_current_a: float | None = None  #: phase rms, optional


@dataclass(frozen=True)
class Sampling:
    rate_hz: float
    voltage_source: str = "measured"  #: "measured" or "reference" (drive's voltage command)


@dataclass(frozen=True)
class Transmission:
    """Gear pair or sprocket-chain drive (paper Table 3)."""

    kind: str  #: "gear" or "chain"
    driving_teeth: int
    driven_teeth: int
    driving_pitch_diameter_mm: float | None = None  #: chain only
    driven_pitch_diameter_mm: float | None = None  #: chain only, informative
    chain_length_mm: float | None = None  #: chain only

    @property
    def ratio(self) -> float:
        """Gear ratio g_r = driven / driving teeth (eq. 20)."""
        return self.driven_teeth / self.driving_teeth


@dataclass(frozen=True)
class DriveProfile:
    motor: Motor
    sampling: Sampling
    transmission: Transmission
    name: str = "drive"

    @property
    def rated_fe_hz(self) -> float:
        """Electrical frequency at rated speed, Hz."""
        return self.motor.rated_speed_rpm / 60.0 * self.motor.pole_pairs

    @property
    def ts(self) -> float:
        """Sampling period T_s, s."""
        return 1.0 / self.sampling.rate_hz

    @property
    def torque_per_watt(self) -> float:
        """T_rated / P_rated of eq. 10, N m / W."""
        return self.motor.rated_torque_nm / self.motor.rated_power_w


_SECTIONS = {"motor": Motor, "sampling": Sampling, "transmission": Transmission}


def _build(cls, table: dict, section: str, source: str):
    known = {f.name: f for f in fields(cls)}
    for key in table:
        if key not in known:
            raise InputError(f"unknown key '{section}.{key}' (known: {', '.join(known)})", source=source)
    values = {}
    for name, f in known.items():
        if name not in table:
            if f.default is MISSING:
                raise InputError(f"missing key '{section}.{name}'", source=source)
            continue
        value = table[name]
        want = str(f.type)
        if "int" in want and "float" not in want:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif "float" in want:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
            value = float(value) if ok else value
        else:
            ok = isinstance(value, str)
        if not ok:
            raise InputError(f"key '{section}.{name}' has the wrong type ({type(value).__name__})", source=source)
        if isinstance(value, (int, float)) and (not math.isfinite(value) or value <= 0):
            raise InputError(f"key '{section}.{name}' must be positive, got {value}", source=source)
        values[name] = value
    return cls(**values)


def parse_profile(data: dict, source: str = "<profile>") -> DriveProfile:
    """Build a profile from a parsed TOML document; errors name ``source`` and the key path."""
    for key in data:
        if key not in _SECTIONS and key != "name":
            raise InputError(f"unknown key '{key}' (known: name, {', '.join(_SECTIONS)})", source=source)
    parts = {}
    for section, cls in _SECTIONS.items():
        table = data.get(section)
        if not isinstance(table, dict):
            raise InputError(f"missing table [{section}]", source=source)
        parts[section] = _build(cls, table, section, source)
    if parts["sampling"].voltage_source not in ("measured", "reference"):
        raise InputError("key 'sampling.voltage_source' must be \"measured\" or \"reference\"", source=source)
    tr = parts["transmission"]
    if tr.kind not in ("gear", "chain"):
        raise InputError("key 'transmission.kind' must be \"gear\" or \"chain\"", source=source)
    if tr.kind == "chain":
        for key in ("driving_pitch_diameter_mm", "chain_length_mm"):
            if getattr(tr, key) is None:
                raise InputError(f"missing key 'transmission.{key}' (required for a chain)", source=source)
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise InputError("key 'name' must be a string", source=source)
    return DriveProfile(name=name, **parts)


def load_profile(path: str | Path) -> DriveProfile:
    """Read and validate a drive profile TOML file."""
    data = read_toml(path, "profile")
    return parse_profile(data, source=str(path))
