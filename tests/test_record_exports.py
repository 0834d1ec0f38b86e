"""Records as people export them from spreadsheets and DAQ tools: separators, decimal commas,
units in the header, any case, a byte-order mark; each variant reads as the same record, and a
unit that does not fit its column is refused naming it."""

from pathlib import Path

import numpy as np
import pytest

from agent.errors import InputError
from agent.records import load_record, stream_record

N = 40
RATE = 25000.0
T = np.arange(N) / RATE
ANGLE = (2 * np.pi * 100 * T) % (2 * np.pi)
V = np.stack([300 * np.cos(ANGLE - k * 2 * np.pi / 3) for k in range(3)])
I = np.stack([8 * np.cos(ANGLE - 0.1 - k * 2 * np.pi / 3) for k in range(3)])
CHANNELS = {"t": T, "va": V[0], "vb": V[1], "vc": V[2], "ia": I[0], "ib": I[1], "ic": I[2], "theta_e": ANGLE}


def _export(path, names: dict, sep=",", comma=False, bom=False, newline="\n", scale=None, extra=None, order=None):
    """Write CHANNELS under the header ``names`` (channel -> header field), values multiplied by
    ``scale`` (channel -> factor, the file's unit), optional ``extra`` columns, a decimal comma."""
    scale = scale or {}
    cols = {names[k]: CHANNELS[k] * scale.get(k, 1.0) for k in names}
    cols.update(extra or {})
    keys = order(list(cols)) if order else list(cols)
    text = sep.join(keys) + newline
    for j in range(N):
        row = [repr(float(cols[k][j])) for k in keys]
        text += sep.join(x.replace(".", ",") if comma else x for x in row) + newline
    path.write_bytes(((("\ufeff" if bom else "") + text)).encode("utf-8"))
    return path


def _same(names):
    return {k: k for k in names}


PLAIN = _same(CHANNELS)
VARIANTS = {
    "comma": dict(names=PLAIN),
    "semicolon": dict(names=PLAIN, sep=";"),
    "semicolon, decimal comma": dict(names=PLAIN, sep=";", comma=True),
    "tab": dict(names=PLAIN, sep="\t"),
    "tab, decimal comma": dict(names=PLAIN, sep="\t", comma=True),
    "bar": dict(names=PLAIN, sep="|"),
    "upper case": dict(names={k: k.upper() for k in CHANNELS}),
    "units in brackets": dict(names={**PLAIN, "va": "va [V]", "ia": "ia [A]", "t": "t [s]", "theta_e": "theta_e [rad]"}),
    "units in parentheses": dict(names={**PLAIN, "vb": "vb (V)", "ib": "ib (A)", "t": "t (s)"}),
    "units as suffix": dict(names={**PLAIN, "vc": "vc_V", "ic": "ic_A", "theta_e": "theta_e_rad"}),
    "milliampere": dict(names={**PLAIN, "ia": "ia [mA]", "ib": "ib [mA]", "ic": "ic [mA]"},
                        scale=dict.fromkeys(("ia", "ib", "ic"), 1e3)),
    "kilovolt": dict(names={**PLAIN, "va": "Va [kV]", "vb": "Vb [kV]", "vc": "Vc [kV]"},
                     scale=dict.fromkeys(("va", "vb", "vc"), 1e-3)),
    "milliseconds": dict(names={**PLAIN, "t": "t [ms]"}, scale={"t": 1e3}),
    "time column named time": dict(names={**PLAIN, "t": "Time [s]"}),
    "angle in degrees": dict(names={**PLAIN, "theta_e": "theta_e [deg]"}, scale={"theta_e": 180 / np.pi}),
    "byte-order mark, semicolon": dict(names=PLAIN, sep=";", bom=True),
    "CRLF line ends": dict(names=PLAIN, newline="\r\n"),
    "CRLF, semicolon, decimal comma, units": dict(names={k: f"{k.upper()} [{u}]" for k, u in zip(
        CHANNELS, ("s", "V", "V", "V", "A", "A", "A", "rad"))}, sep=";", comma=True, newline="\r\n"),
    "unit case": dict(names={**PLAIN, "ia": "IA [ma]", "ib": "IB [MA]", "ic": "IC [mA]"},
                      scale=dict.fromkeys(("ia", "ib", "ic"), 1e3)),
    "shuffled with other columns": dict(names=PLAIN, extra={"temperature [C]": np.full(N, 40.0),
                                                            "t_motor": np.full(N, 1.0), "speed_rpm": np.full(N, 1500.0)},
                                        order=lambda k: k[::-1]),
    "padded fields": dict(names={k: f"  {k} " for k in CHANNELS}),
    "semicolon, units, shuffled": dict(names={**PLAIN, "ia": "ia [A]", "t": "t [s]"}, sep=";", order=sorted),
}


@pytest.mark.parametrize("variant", VARIANTS)
def test_an_export_variant_reads_as_the_same_record(variant, tmp_path):
    path = _export(tmp_path / "rec.csv", **VARIANTS[variant])
    rec = load_record(path)
    np.testing.assert_allclose(rec.t, T, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(rec.v_abc, V, rtol=1e-12)
    np.testing.assert_allclose(rec.i_abc, I, rtol=1e-12)
    np.testing.assert_allclose(rec.theta_e, ANGLE, rtol=1e-12, atol=1e-12)
    assert rec.rate_hz == pytest.approx(RATE, rel=1e-9)
    # streaming reads the same file the same way, chunk by chunk
    chunks = list(stream_record(path, chunk_samples=15))
    np.testing.assert_allclose(np.hstack([c.i_abc for c in chunks]), I, rtol=1e-12)


REFUSED = {
    "a current in volts": ({**PLAIN, "ia": "ia [V]"}, "column 'ia [V]': unit 'V' is not one of A's (A, mA, kA)"),
    "an unknown unit": ({**PLAIN, "va": "va [furlong]"}, "column 'va [furlong]': unit 'furlong' is not one of V's"),
    "a suffixed unit of another quantity": ({**PLAIN, "ib": "ib_V"}, "column 'ib_V': unit 'V' is not one of A's"),
    "time in volts": ({**PLAIN, "t": "t (V)"}, "column 't (V)': unit 'V' is not one of s's"),
    "the same channel twice": ({**PLAIN, "ia": "ia [A]"}, None),
}


@pytest.mark.parametrize("case", REFUSED)
def test_a_unit_that_does_not_fit_its_column_is_refused_naming_it(case, tmp_path):
    names, message = REFUSED[case]
    extra = {"IA (mA)": CHANNELS["ia"] * 1e3} if message is None else None
    path = _export(tmp_path / "rec.csv", names, extra=extra)
    with pytest.raises(InputError) as err:
        load_record(path)
    text = str(err.value)
    assert text.startswith(f"{path}: ")
    assert (message or "duplicate column 'ia' ('ia [A]' and 'IA (mA)')") in text


def test_semicolon_file_missing_a_column_names_the_columns_it_found(tmp_path):
    path = _export(tmp_path / "rec.csv", {k: k for k in CHANNELS if k != "vc"}, sep=";", comma=True)
    with pytest.raises(InputError, match=r"missing required column 'vc' \(found: t, va, vb, ia, ib, ic, theta_e\)"):
        load_record(path)


def test_a_profile_and_an_agent_config_saved_with_a_byte_order_mark_load(tmp_path):
    from agent.profile import load_profile
    from agent.runtime.config import load_config

    root = Path(__file__).resolve().parent.parent
    for name, src in (("p.toml", root / "config/profiles/rig_gear.toml"), ("agent.toml", root / "config/agent.toml")):
        (tmp_path / name).write_bytes(b"\xef\xbb\xbf" + src.read_bytes())
    assert load_profile(tmp_path / "p.toml").motor.pole_pairs == 4
    text = (tmp_path / "agent.toml").read_text(encoding="utf-8-sig").replace("profiles/", str(root / "config/profiles") + "/")
    (tmp_path / "agent.toml").write_bytes(b"\xef\xbb\xbf" + text.encode())
    assert load_config(tmp_path / "agent.toml").drives
