"""Write docs/figures.md from the benchmarks' own output (``benchmarks/results/<name>.json``,
written by each benchmark through ``benchmarks/figures_json.py``): each figure with the command
that produced it, the machine it ran on and the date.

    python scripts/gen_figures.py            # write docs/figures.md
    python scripts/gen_figures.py --check    # exit 1 when docs/figures.md is not what the results give

``python benchmarks/run_all.py`` runs every benchmark (and so refreshes every result file).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "figures.md"
LIMIT_BYTES = 30_000

HEAD = """# Figures

Every figure on this page is what a benchmark in `benchmarks/` printed, with the command that
produced it, the machine it ran on (CPU, cores, the load average before and after, Python and
numpy) and when. The page is generated: `python benchmarks/run_all.py` runs every benchmark
(each writes `benchmarks/results/<name>.json`), then `python scripts/gen_figures.py` writes this
page; CI's `python scripts/gen_figures.py --check` fails when the page is not what the results
give. A figure measured beside two busy processes (`python -c "while True: pass"` twice, killed by
id after) stands for a lab PC running ROS, a browser and an IDE beside the acquisition.

Paths such as `../shared/data/kuka_lwr4/` are the shared KUKA LWR4+ recordings beside the
repository (see [From someone else's logs](guides/logs.md)).
"""


@dataclass(frozen=True)
class Section:
    title: str  # its anchor is what the docs link to (e.g. figures.md#real-time-on-a-busy-machine)
    intro: str
    results: tuple[str, ...]  # the names of benchmarks/results/<name>.json, in order


SECTIONS = (
    Section("Real time on a busy machine",
            "The whole demo, the timing-sensitive tests, the CANopen bus and the Dynamixel arm's excitation, each "
            "beside two busy processes; the serial rig's recording beside one pinned to CPU 0, with the machine's own stalls.",
            ("demo_busy2", "realtime_busy2", "canopen_busy2", "dynamixel_excite_busy2", "serial_load")),
    Section("The estimator service",
            "`armid demo` runs the service's path: its experiments stream to an estimator service, whose published "
            "fits are compared with the fit of the complete recording (equal when no record was missed); the "
            "truth check compares the identified parameters with the simulated arm's.",
            ("demo",)),
    Section("Identification accuracy",
            "The declared model's fit and held-out error: the shipped PUMA 560 example and the real KUKA LWR4+ "
            "recordings. How the errors are measured: [Methods](methods.md).",
            ("puma_identify", "kuka_identify")),
    Section("Diagnosis on the KUKA LWR4+",
            "What the declared model lacks on the real KUKA LWR4+ recordings. How to read it: "
            "[Diagnosis](guides/diagnosis.md).",
            ("kuka_diagnose",)),
    Section("armid check",
            "A tool (0.5-5 kg) on simulated arms, found by `armid check` against the identified model, and "
            "tool-free runs that must hold with nothing named.",
            ("check_cases",)),
    Section("What a user waits for",
            "Whole processes against a reference in the same run, interleaved, best and median: the command "
            "line's start against `python -c \"import numpy\"`, `armid identify` against a plain Pinocchio and "
            "`lstsq` script, `armid diagnose` against the plain pipeline (`../shared/tools/baseline.py`).",
            ("startup", "identify_process", "diagnose_process")),
    Section("Speed",
            "The regressor, identification, diagnosis and the trajectory design against their references, "
            "in the same process.",
            ("regressor", "identify", "diagnose", "design")),
    Section("Physically consistent parameters",
            "The physically consistent fit against the unconstrained one.",
            ("feasible",)),
    Section("On-line payload estimation",
            "The payload estimator's cost on replay and live.",
            ("payload",)),
    Section("Acquisition and recording",
            "Acquisition to a Zenoh subscriber in another process, and the recording's size and fidelity.",
            ("daq", "recording")),
    Section("rosbag2 bags",
            "A ROS 2 arm's bag read against the CSV of the same data ([Your ROS 2 arm](guides/ros2.md)).",
            ("bags",)),
    Section("The CANopen bus",
            "6 axes at 2 ms, quiet (beside two busy processes: [Real time on a busy machine](#real-time-on-a-busy-machine)).",
            ("canopen",)),
    Section("Dynamixel chain",
            "6 servos over a pseudo-terminal at 4 Mbaud: the chain's timing, then a whole-arm excitation and its "
            "recording identified.",
            ("dynamixel", "dynamixel_excite")),
    Section("A lab's fleet",
            "`armid fleet` on Ray: 2 workers against 1, and the same results.",
            ("fleet",)),
)


def machine_line(doc: dict[str, Any]) -> str:
    m = doc["machine"]
    before, after = m["load_average_before"], m["load_average_after"]
    return (f"{m['cpu']}, {m['cores']} cores, load average {before[0]:.2f} before and {after[0]:.2f} after; "
            f"{m['system']}, Python {m['python']}, numpy {m['numpy']}; {doc['date']}, {doc['seconds']:g} s")


def render_result(name: str, results: dict[str, dict[str, Any]]) -> list[str]:
    doc = results.get(name)
    if doc is None:
        return [f"`{name}`: not measured yet (`python benchmarks/run_all.py {name}`).", ""]
    return [f"`{doc['command']}`", "", f"*{machine_line(doc)}*", "", "```text", *doc["output"], "```", ""]


def render(results: dict[str, dict[str, Any]]) -> str:
    placed = {name for s in SECTIONS for name in s.results}
    stray = sorted(set(results) - placed)
    if stray:
        raise SystemExit(f"results in no section of scripts/gen_figures.py: {', '.join(stray)}")
    lines = [HEAD]
    for section in SECTIONS:
        lines += [f"## {section.title}", "", section.intro, ""]
        for name in section.results:
            lines += render_result(name, results)
    return "\n".join(lines).rstrip("\n") + "\n"


def load_results(where: Path = RESULTS) -> dict[str, dict[str, Any]]:
    out = {}
    for path in sorted(where.glob("*.json")):
        doc = json.loads(path.read_text())
        if doc.get("name") != path.stem:
            raise SystemExit(f"{path}: its name is {doc.get('name')!r}, not {path.stem!r}")
        out[path.stem] = doc
    return out


def main(argv: list[str]) -> int:
    text = render(load_results())
    size = len(text.encode())
    if size > LIMIT_BYTES:
        print(f"docs/figures.md would be {size} bytes; the limit is {LIMIT_BYTES}: shorten a benchmark's output", file=sys.stderr)
        return 1
    if "--check" in argv:
        if not PAGE.exists() or PAGE.read_text() != text:
            print("docs/figures.md is not what benchmarks/results/ give: run python scripts/gen_figures.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    print(f"wrote {PAGE.relative_to(ROOT)} ({size} bytes, {len(load_results())} results)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
