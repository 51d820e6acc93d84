"""Damaged MCAP recordings: every readable chunk is read, and the loss is said in records,
seconds and bytes (issue 18).

The recording is the shipped PUMA 560 example written by the recorder itself
(``daq.recorder.McapRecorder``: zstd chunks of about 16 KiB of messages, summary with the chunk index,
footer). Damage: bytes flipped inside one chunk (its CRC fails), a chunk's length field
garbled (the framing breaks: reading resumes at the next chunk, found through the summary's
chunk index, or byte by byte when there is no summary), the footer or the whole summary
missing (nothing lost), the file cut mid-chunk.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from armid.cli import main
from armid.daq.recorder import McapRecorder
from armid.drivers.interface import Sample
from armid.io.recordings import read_mcap_arrays, read_recording
from armid.io.robot_file import load_robot
from armid.io.ros2_cdr import typestore
from armid.schema.joint_states import JointStates

ROOT = Path(__file__).resolve().parent.parent
PUMA = ROOT / "config" / "robots" / "puma560.yaml"
EXAMPLE = ROOT / "examples" / "puma560_excitation.csv"
VALIDATION = ROOT / "examples" / "puma560_validation.csv"


@pytest.fixture(scope="module")
def intact(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The example recording (5,000 samples at 2 ms) as ``armid record`` writes it."""
    robot = load_robot(PUMA)
    rec = read_recording(EXAMPLE, robot)
    kt = np.array([j.torque_constant for j in robot.joints])
    path = tmp_path_factory.mktemp("mcap") / "run.mcap"
    typestore()  # the codec built before the recorder opens: it closes a chunk 0.25 s after the last one, by the clock
    recorder = McapRecorder(path, [j.name for j in robot.joints], {"robot": robot.name})
    n = robot.n_joints
    assert rec.qd is not None
    for k in range(rec.n_samples):
        current = rec.tau[k] / kt
        recorder.write(JointStates.of_sample(k, Sample(k, float(rec.t[k]), np.ones(n, bool), rec.q[k], rec.qd[k], np.ones(n, bool),
                                                  current, current, np.full(n, 0x27), rec.tau[k])))
    recorder.close()
    return path


def _chunks(path: Path) -> list[int]:
    """Where each chunk starts, from the summary's chunk index (the ``mcap`` library's reader)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 100
    return sorted(c.chunk_start_offset for c in summary.chunk_indexes)


def _write(path: Path, data: bytes | bytearray) -> Path:
    path.write_bytes(bytes(data))
    return path


def test_intact_recording_reads_whole_without_notes(intact: Path) -> None:
    arrays, metadata, notes = read_mcap_arrays(intact)
    assert notes == [] and metadata["robot"] == "puma560"
    assert np.array_equal(arrays["sequence"], np.arange(5000))


def test_flipped_chunk_is_left_out_said_and_identifies_the_same(intact: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    starts = _chunks(intact)
    data = bytearray(intact.read_bytes())
    hit = starts[len(starts) // 2]
    data[hit + 700 : hit + 716] = bytes(b ^ 0x5A for b in data[hit + 700 : hit + 716])
    bad = _write(tmp_path / "flipped.mcap", data)
    whole, _, _ = read_mcap_arrays(intact)
    arrays, _, notes = read_mcap_arrays(bad)
    lost = sorted(set(whole["sequence"].tolist()) - set(arrays["sequence"].tolist()))
    # one chunk is gone, every other one is read
    assert 20 < len(lost) < 60 and lost == list(range(lost[0], lost[-1] + 1)) and len(arrays["sequence"]) == 5000 - len(lost)
    assert len(notes) == 1, notes
    said = re.fullmatch(r"a chunk that fails its CRC \(bytes (\d+)\.\.(\d+) of (\d+)\): (\d+) records \(([\d.]+) s; sequence (\d+)\.\.(\d+), "
                        r"between t ([\d.]+) and ([\d.]+) s\) lost; reading resumed after it", notes[0])
    assert said, notes[0]
    assert int(said.group(1)) == hit and int(said.group(4)) == len(lost)
    assert float(said.group(5)) == pytest.approx(0.002 * len(lost), abs=1e-6)
    assert (int(said.group(6)), int(said.group(7))) == (lost[0], lost[-1])
    # identification: the same result within noise
    docs = []
    for path in (intact, bad):
        out = tmp_path / f"{path.stem}.json"
        assert main(["identify", str(path), "--robot", str(PUMA), "--validate", str(VALIDATION), "--json", str(out)]) == 0
        docs.append(json.loads(out.read_text()))
    err = capsys.readouterr().err
    assert f"{bad}: a chunk that fails its CRC" in err
    a, b = ([p for p in d["base_parameters"]] for d in docs)
    assert [p["expression"] for p in a] == [p["expression"] for p in b]
    shift = max(abs(p["value"] - q["value"]) / p["std"] for p, q in zip(a, b))
    assert shift < 0.5, f"a base parameter moved by {shift:.2f} standard deviations"
    assert docs[1]["validation"]["relative_error"] == pytest.approx(docs[0]["validation"]["relative_error"], rel=0.02)


def test_garbled_chunk_length_resumes_at_the_next_chunk(intact: Path, tmp_path: Path) -> None:
    """The framing breaks: the summary's chunk index says where the next chunk starts; without
    a summary the next whole chunk with a matching CRC is found byte by byte."""
    starts = _chunks(intact)
    data = bytearray(intact.read_bytes())
    hit = starts[40]
    data[hit + 3] ^= 0x5A  # the chunk's record length
    with_summary = _write(tmp_path / "indexed.mcap", data)
    data_end = data.rfind(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")  # DataEnd: the summary follows
    without_summary = _write(tmp_path / "scanned.mcap", data[:data_end])
    counts = []
    for path in (with_summary, without_summary):
        arrays, _, notes = read_mcap_arrays(path)
        counts.append(len(arrays["sequence"]))
        assert re.match(rf"unreadable record framing \(bytes {hit}\.\.\d+ of \d+\): (\d+) records \([\d.]+ s; sequence \d+\.\.\d+", notes[0])
        assert int(re.search(r"\): (\d+) records", notes[0]).group(1)) == 5000 - counts[-1]  # type: ignore[union-attr]
    assert counts[0] == counts[1] and 4900 < counts[0] < 5000


def test_missing_footer_or_summary_loses_nothing(intact: Path, tmp_path: Path) -> None:
    data = intact.read_bytes()
    no_footer = _write(tmp_path / "no_footer.mcap", data[:-37])  # footer record (29 bytes) and closing magic
    data_end = data.rfind(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")
    no_summary = _write(tmp_path / "no_summary.mcap", data[: data_end + 13])  # DataEnd kept, summary and footer gone
    for path in (no_footer, no_summary):
        arrays, _, notes = read_mcap_arrays(path)
        assert notes == [] and len(arrays["sequence"]) == 5000, (path.name, notes)


def test_cut_file_says_how_much_of_the_cut_chunk_is_lost(intact: Path, tmp_path: Path) -> None:
    starts = _chunks(intact)
    data = intact.read_bytes()
    cut_chunk = starts[60]
    cut = _write(tmp_path / "cut.mcap", data[: cut_chunk + 5000])
    arrays, _, notes = read_mcap_arrays(cut)
    whole, _, _ = read_mcap_arrays(intact)
    # the records the cut chunk held: those between the one before it and the one after it
    next_first = read_mcap_arrays(_write(tmp_path / "two.mcap", data[: starts[61] + 1]))[0]["sequence"][-1] + 1
    in_chunk = int(next_first - len(arrays["sequence"]))
    assert len(arrays["sequence"]) < len(whole["sequence"]) and len(notes) == 1
    said = re.fullmatch(r"the file ends inside a chunk \(bytes \d+\.\.\d+ of \d+\): a cut chunk of about (\d+) records \(([\d.]+) s\) "
                        r"after sequence (\d+) \(t [\d.]+ s\) lost; the rest of the run is lost", notes[0])
    assert said, notes[0]
    assert int(said.group(1)) == in_chunk and float(said.group(2)) == pytest.approx(0.002 * in_chunk, abs=1e-6)
    assert int(said.group(3)) == len(arrays["sequence"]) - 1


def test_first_chunk_lost_without_summary_still_reads_the_rest(intact: Path, tmp_path: Path) -> None:
    """The channel record lives in the first chunk only (and in the summary): with both gone,
    the messages of the one remaining channel are still read, and said so."""
    starts = _chunks(intact)
    data = bytearray(intact.read_bytes())
    data[starts[0] + 900 : starts[0] + 910] = bytes(10)
    data_end = data.rfind(b"\x0f\x04\x00\x00\x00\x00\x00\x00\x00")
    arrays, _, notes = read_mcap_arrays(_write(tmp_path / "headless.mcap", data[:data_end]))
    first = int(arrays["sequence"][0])
    assert 20 < first < 60 and np.array_equal(arrays["sequence"], np.arange(first, 5000))
    assert re.match(rf"a chunk that fails its CRC \(bytes {starts[0]}\.\.\d+ of \d+\): {first} records \(", notes[0]), notes
    assert "channel record was lost" in notes[-1]
