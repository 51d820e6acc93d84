"""Khosla's 5-point filter and the cleaning of imperfect controller logs."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ROBOTS

from armid.identify.differentiation import five_point_derivative, sharpened_five_point_derivative
from armid.identify.errors import RecordingError
from armid.identify.filtering import lowpass
from armid.identify.preprocess import PrepareOptions, prepare
from armid.io.recordings import Recording, read_recording, write_csv
from armid.io.robot_file import load_robot


def test_five_point_filter_is_exact_on_parabolas():  # type: ignore[no-untyped-def]
    t = np.arange(0.0, 1.0, 0.002)
    x = 3.0 - 2.0 * t + 5.0 * t**2
    d = five_point_derivative(x, 0.002)
    assert np.all(np.isnan(d[:2])) and np.all(np.isnan(d[-2:]))
    assert np.allclose(d[2:-2], -2.0 + 10.0 * t[2:-2], atol=1e-9)


def test_causal_form_is_the_same_filter_two_samples_late():  # type: ignore[no-untyped-def]
    t = np.arange(0.0, 1.0, 0.002)
    x = np.sin(3 * t)[:, None] * [1.0, 2.0]
    causal = five_point_derivative(x, 0.002, causal=True)
    centred = five_point_derivative(x, 0.002)
    assert np.all(np.isnan(causal[:4]))
    assert np.allclose(causal[4:], centred[2:-2])
    parabola = 1.0 + t**2
    assert np.allclose(five_point_derivative(parabola, 0.002, causal=True)[4:], 2 * t[2:-2])


def test_noise_gain_against_central_difference():  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(0)
    noise = rng.normal(size=200_000)
    period = 0.002
    five = np.nanstd(five_point_derivative(noise, period))
    central = np.std((noise[2:] - noise[:-2]) / (2 * period))
    # theory: sqrt(10)/10 / T against sqrt(2)/2 / T, a ratio of 0.447
    assert five * period == pytest.approx(np.sqrt(10) / 10, rel=0.01)
    assert five / central == pytest.approx(np.sqrt(10) / 10 / (np.sqrt(2) / 2), rel=0.01)


def test_sharpened_filter_is_exact_on_quartics_and_flat_in_the_band_where_the_plain_one_droops():  # type: ignore[no-untyped-def]
    t = np.arange(0.0, 1.0, 0.002)
    x = 1.0 + t - 3.0 * t**2 + 2.0 * t**3 - 4.0 * t**4
    d = sharpened_five_point_derivative(x, 0.002)
    assert np.all(np.isnan(d[:4])) and np.all(np.isnan(d[-4:]))
    assert np.allclose(d[4:-4], (1.0 - 6.0 * t + 6.0 * t**2 - 16.0 * t**3)[4:-4], atol=1e-9)
    # a 3 Hz harmonic at 2 ms: the plain filter's gain is 1 - 17 (wT)^2 / 30 (0.08 % low,
    # which reads every inertia that much high); the sharpened one is flat to 1e-6
    t = np.arange(0.0, 4.0, 0.002)
    w = 2 * np.pi * 3.0
    truth = w * np.cos(w * t)
    inner = slice(10, -10)
    plain = five_point_derivative(np.sin(w * t), 0.002)[inner] @ truth[inner] / (truth[inner] @ truth[inner])
    sharp = sharpened_five_point_derivative(np.sin(w * t), 0.002)[inner] @ truth[inner] / (truth[inner] @ truth[inner])
    assert plain == pytest.approx(1 - 17 * (w * 0.002) ** 2 / 30, rel=1e-5) and abs(sharp - 1) < 2e-6
    # the price: 27 % more white-noise gain (sqrt(0.1628) against sqrt(0.1))
    noise = np.random.default_rng(2).normal(size=200_000)
    ratio = np.nanstd(sharpened_five_point_derivative(noise, 1.0)) / np.nanstd(five_point_derivative(noise, 1.0))
    assert ratio == pytest.approx(np.sqrt(0.1628 / 0.1), rel=0.01)


def test_zero_phase_lowpass_keeps_slow_signal_in_phase():  # type: ignore[no-untyped-def]
    t = np.arange(0.0, 4.0, 0.002)
    slow = np.sin(2 * np.pi * 1.0 * t)
    noisy = slow + 0.2 * np.random.default_rng(1).normal(size=t.size)
    out = lowpass(noisy, 0.002, 10.0)
    assert np.std((out - slow)[200:-200]) < 0.05
    assert np.std((out - slow)[:200]) < 0.05 and np.std((out - slow)[-200:]) < 0.05  # the ends too
    with pytest.raises(ValueError, match="cut-off"):
        lowpass(noisy, 0.002, 400.0)


@pytest.mark.parametrize("shape, axis", [((3000,), 0), ((2500, 7), 0), ((3, 2000, 130), 1), ((41,), 0)])
def test_the_compiled_lowpass_is_scipys_sosfiltfilt_to_the_bit(shape, axis):  # type: ignore[no-untyped-def]
    """identify/kernels/filter.py against scipy's own forward-backward filter on the same
    extended signal: any difference in the recursion's arithmetic shows in the last bit."""
    from scipy.signal import butter, sosfiltfilt

    from armid.identify.filtering import _extrapolate

    period, cutoff = 0.002, 9.7
    x = np.cumsum(np.random.default_rng(3).normal(size=shape), axis=axis)
    span = int(np.ceil(1.0 / (cutoff * period)))
    flat = np.moveaxis(x, axis, 0).reshape(x.shape[axis], -1)
    n, fit, pad = flat.shape[0], min(flat.shape[0], max(8, 2 * span)), 4 * span
    extended = np.concatenate([_extrapolate(flat[:fit][::-1], pad)[::-1], flat, _extrapolate(flat[n - fit :], pad)])
    sos = butter(4, cutoff / (0.5 / period), output="sos")  # the cut-off as a fraction of Nyquist, computed as lowpass does
    reference = sosfiltfilt(sos, extended, axis=0, padtype="odd", padlen=min(pad, 15))[pad : pad + n]
    out = np.moveaxis(lowpass(x, period, cutoff, axis=axis), axis, 0).reshape(n, -1)
    assert np.array_equal(out, reference)


def _recording(t, q, tau, qd=None):  # type: ignore[no-untyped-def]
    return Recording("mem.csv", t, q, tau, qd, None, np.arange(2, t.size + 2), [])


def test_jittery_1khz_log_is_resampled_and_said():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    rng = np.random.default_rng(3)
    steps = rng.uniform(0.0007, 0.0013, 3000)
    steps[::300] = 0.009  # occasional 9 ms stalls
    t = np.cumsum(steps)
    q = np.column_stack([np.sin(t), 0.5 * np.cos(2 * t)])
    prep = prepare(_recording(t, q, q.copy()), robot, PrepareOptions(lowpass_hz=None))
    assert any("resampled" in n for n in prep.notes)
    seg = prep.segments[0]
    assert np.allclose(np.diff(seg.t), np.diff(seg.t)[0])
    assert np.allclose(seg.qd[:, 0], np.cos(seg.t), atol=2e-3)
    assert np.allclose(seg.qdd[:, 0], -np.sin(seg.t), atol=2e-2)


def test_100hz_log_with_gaps_is_split_not_bridged():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    t = np.arange(0.0, 10.0, 0.01)
    t = np.concatenate([t[:300], t[334:700], t[733:]])  # two gaps of a third of a second
    q = np.column_stack([np.sin(t), np.cos(t)])
    prep = prepare(_recording(t, q, q.copy()), robot, PrepareOptions(lowpass_hz=None))
    assert len(prep.segments) == 3
    assert any("split at 2 gap" in n for n in prep.notes)
    for seg in prep.segments:
        assert np.max(np.diff(seg.t)) < 0.011


def test_garbage_rows_are_dropped_with_their_lines(tmp_path):  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    t = np.arange(0.0, 2.0, 0.002)
    q = np.column_stack([np.sin(t), np.cos(t)])
    path = tmp_path / "log.csv"
    write_csv(path, t, {"q": q, "tau": q})
    lines = path.read_text().splitlines()
    lines[101] = "0.2,nan,1,0,1"  # NaN
    lines[201] = "0,0,0,0,0"  # time backwards and zeros
    lines[301] = lines[301].split(",")[0] + ",2.9,1,0,1"  # position jump
    lines[401] = "garbage"  # wrong field count
    path.write_text("\n".join(lines) + "\n")
    prep = prepare(read_recording(path, robot), robot, PrepareOptions(lowpass_hz=None))
    notes = {n.split(":")[0] + ":" + n.split(":")[1].split("(")[0]: n for n in prep.notes if n.startswith("dropped")}
    assert "102, 402" in notes["dropped 2 row(s): non-numeric or non-finite value "]
    assert "line 202" in notes["dropped 1 row(s): time not increasing "]
    assert "line 302" in notes["dropped 1 row(s): position jump beyond the joint's velocity limit "]
    assert prep.dropped_rows == 4
    assert any("velocity from positions" in n for n in prep.notes)


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "empty file"),
        ("t,q1,q2\n0,1,2\n", "neither torque"),
        ("t,q1,tau1,tau2\n0,1,2,3\n", "q2 missing"),
        ("t,q1,q2,q3,tau1,tau2\n0,1,2,3,4,5\n", "column q3 but planar2 has 2 joints"),
        ("q1,q2,tau1,tau2\n", "no time column"),
    ],
)
def test_malformed_csv_names_what_is_wrong(tmp_path, content, message):  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(RecordingError, match=message) as err:
        read_recording(path, robot)
    assert "bad.csv" in str(err.value)


def test_corrupt_npz_is_a_recording_error(tmp_path):  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    path = tmp_path / "x.npz"
    path.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(RecordingError, match="x.npz"):
        read_recording(path, robot)


def test_too_few_rows_is_refused():  # type: ignore[no-untyped-def]
    robot = load_robot(ROBOTS / "planar2.yaml")
    t = np.arange(0.0, 0.01, 0.002)
    q = np.zeros((t.size, 2))
    with pytest.raises(RecordingError, match="usable rows"):
        prepare(_recording(t, q, q), robot, PrepareOptions())
