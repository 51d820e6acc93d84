"""Dependencies point one way: every import of every module, read from the source (ast).

Layers, bottom to top (``armid/__init__.py`` draws them)::

    armid.schema                      imports nothing of armid's
    armid.resources, armid.config     imports nothing of armid's (the package data and its finder)
    armid.identify                    schema
    armid.drivers                     schema, resources (the drives' dictionaries)
    armid.io                          schema, identify, drivers (the rig's types)
    armid.daq                         schema, identify, io, drivers
    armid.sim_bus                     schema, identify, drivers, resources (a peer on the bus; a rig comes parsed)
    armid (cli, demo, report, ...)    anything

Every module is in exactly one of these layers, by its package: no module is counted in
another's. Only the top layer (or a test) starts the simulator: nothing below imports
``armid.sim_bus``; and only the top layer and ``io`` read files: ``sim_bus`` takes a parsed rig.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
FOLDERS = {"armid": "armid", "armid.identify": "identify", "armid.daq": "daq", "armid.drivers": "drivers",
           "armid.sim_bus": "sim_bus", "armid.config": "config"}
ALLOWED = {
    "schema": {"schema"},
    "resources": {"resources"},
    "identify": {"schema", "identify"},
    "drivers": {"schema", "resources", "drivers"},
    "io": {"schema", "identify", "drivers", "io"},
    "daq": {"schema", "identify", "io", "drivers", "daq"},
    "sim_bus": {"schema", "identify", "drivers", "resources", "sim_bus"},
    "app": {"schema", "resources", "identify", "io", "drivers", "daq", "sim_bus", "app"},
}
IO_LIBRARIES = {"yaml", "mcap", "mcap_ros2", "rosbags", "zenoh", "can", "canopen", "serial", "matplotlib"}


def layer(module: str) -> str:
    parts = module.split(".")
    if parts[0] != "armid":
        raise ValueError(module)
    if len(parts) == 1:
        return "app"
    second = parts[1]
    if second == "config":  # the package data, served by armid.resources
        return "resources"
    if second in ("schema", "resources", "identify", "drivers", "io", "daq", "sim_bus"):
        return second
    return "app"


def modules() -> list[tuple[str, Path]]:
    out = []
    for package, folder in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([package, *parts])
            if package == "armid" and parts and parts[0] in ("identify", "daq", "drivers", "sim_bus"):
                continue
            out.append((name, path))
    return out


def imports(module: str, path: Path) -> list[tuple[str, int]]:
    """Every module ``module`` imports (function-level imports too), absolute, with its line."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_package else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, node.lineno))
            if node.level and not node.module:  # "from . import x": x may be a module
                out += [(f"{target}.{a.name}", node.lineno) for a in node.names]
    return out


def test_every_package_is_found() -> None:
    names = {m for m, _ in modules()}
    for expected in ("armid.schema.errors", "armid.schema.joint_state", "armid.identify.dynamics", "armid.io.recordings",
                     "armid.drivers.interface", "armid.daq.recorder", "armid.sim_bus.arm", "armid.cli"):
        assert expected in names


def test_imports_point_one_way() -> None:
    wrong = []
    for module, path in modules():
        own = layer(module)
        for target, line in imports(module, path):
            if target.split(".")[0] != "armid":
                continue
            if target in ("armid",) and own != "app":
                wrong.append(f"{path.relative_to(ROOT)}:{line}: {module} ({own}) imports the top-level package armid")
                continue
            other = layer(target)
            if other not in ALLOWED[own]:
                wrong.append(f"{path.relative_to(ROOT)}:{line}: {module} ({own}) imports {target} ({other})")
    assert not wrong, "imports against the direction:\n" + "\n".join(wrong)


def test_identify_imports_no_io_library() -> None:
    wrong = []
    for module, path in modules():
        if layer(module) != "identify":
            continue
        for target, line in imports(module, path):
            if target.split(".")[0] in IO_LIBRARIES:
                wrong.append(f"{path.relative_to(ROOT)}:{line}: {module} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_resources_and_sim_bus_sit_where_the_layers_say() -> None:
    """Issue 32: ``armid.resources`` was counted as the schema layer, which hid the drivers'
    and the simulator's imports of it; ``sim_bus`` parsed rig files (``armid.io``)."""
    assert layer("armid.resources") == "resources" and layer("armid.schema.errors") == "schema"
    assert "resources" not in ALLOWED["schema"] and "resources" not in ALLOWED["identify"]
    assert "io" not in ALLOWED["sim_bus"]


def test_the_checker_sees_a_wrong_import(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from ..io.recordings import read_recording\n    import yaml\n")
    found = imports("armid.identify.bad", bad)
    assert ("armid.io.recordings", 2) in found and ("yaml", 3) in found
    assert layer("armid.io.recordings") not in ALLOWED["identify"]


def test_every_package_is_installed() -> None:
    """Each folder with an ``__init__.py`` is a package the wheel lists (``pyproject.toml``)."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = set()
    for package, folder in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT / folder).parts
            if package == "armid" and parts and parts[0] in ("identify", "daq", "drivers", "sim_bus"):
                continue
            found.add(".".join([package, *parts]))
    assert found == listed, (sorted(found - listed), sorted(listed - found))


def private_imports(module: str, path: Path) -> list[str]:
    """Every ``_name`` (or name from a ``_module``) ``module`` imports from another armid module,
    function-level imports too, as ``path:line name``: a seam between modules is public."""
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom) or not (node.level or (node.module or "").startswith("armid")):
            continue
        private_module = any(p.startswith("_") and not p.startswith("__") for p in (node.module or "").split("."))
        for a in node.names:
            if private_module or (a.name.startswith("_") and not a.name.startswith("__")):
                out.append(f"{path.relative_to(ROOT) if path.is_relative_to(ROOT) else path}:{node.lineno} {a.name}")
    return out


def test_no_private_name_is_imported_across_modules() -> None:
    wrong = [p for module, path in modules() for p in private_imports(module, path)]
    assert not wrong, "private names imported from another module (make the seam public):\n" + "\n".join(wrong)


def test_the_private_import_checker_sees_one(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text("from .data import _stack, StackedData\ndef f():\n    from armid.identify.kernels._lanes import rows\n")
    assert private_imports("armid.identify.bad", bad) == [f"{bad}:1 _stack", f"{bad}:3 rows"]


def test_the_client_does_not_know_its_drives_are_simulated() -> None:
    """Pacing is the rig's setting: no driver or simulator file sniffs the simulator's product code."""
    wrong = [str(p.relative_to(ROOT)) for folder in ("drivers", "sim_bus") for p in sorted((ROOT / folder).rglob("*.py"))
             if "SIMULATED_PRODUCT_CODE" in p.read_text() or "paced_by_drives" in p.read_text()]
    assert not wrong, wrong


def test_the_service_identifies_from_memory() -> None:
    """``armid serve`` reads each experiment's records where they are, in memory; its run.mcap is the archive's."""
    text = (ROOT / "armid" / "serve.py").read_text()
    assert "read_recording(" not in text and "load_run(" not in text
