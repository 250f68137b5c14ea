"""The package's import graph: no cycle, the core ROS-free and pointing one way, nodes never reaching into a
command-line tool.  Read from the source (every import, also those inside functions and under
TYPE_CHECKING), so an arrow cannot hide in a lazy import."""
import ast
import dataclasses
import os
import re
from pathlib import Path

import numpy as np
import pytest

PACKAGE = "piezo_valve_ros"
ROOT = Path(__file__).resolve().parent.parent / PACKAGE

# what each part of the core may import from the rest of the core (besides itself and the shared leaves)
SHARED_LEAVES = {"core.metrics", "core.validation", "core.defaults", "core.errors", "core.blas"}
MAY_IMPORT = {
    "core.model": set(),
    "core.control": {"core.model"},
    "core.sim": {"core.model", "core.control"},
    "core.identification": {"core.model", "core.control"},
    "core.tuning": {"core.model", "core.control", "core.sim"},
    "core.monitoring": {"core.model", "core.control", "core.identification"},
    "core.runs": set(),
}
# what each folder outside the core may import from the package besides the core and itself (the layout's
# layers: io, runtime and backends on the core; ros the ROS plumbing; rig on it; the nodes; the tools)
FOLDER_MAY_IMPORT = {
    "io": set(),
    "runtime": {"io", "backends"},
    "backends": set(),
    "ros": {"io", "runtime"},
    "rig": {"io", "runtime", "ros"},
    "nodes": {"io", "runtime", "backends", "ros", "rig", "identify"},
    "identify": {"io"},
    "cli": {"io", "runtime", "backends", "ros", "rig", "nodes", "identify"},
}
TOP_LEVEL = {"__init__.py", "identify.py"}   # the package's own modules: the library face of identification


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(module -> package modules it imports, module -> top-level names of everything it imports)."""
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    edges, externals = {}, {}
    for name, path in files.items():
        package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        found, outside = set(), set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package[:len(package) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != PACKAGE:
                    outside.add(target.split(".")[0])
                    continue
                for alias in node.names:
                    candidate = f"{target}.{alias.name}"
                    found.add(candidate if candidate in files else target)
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    (found if alias.name.split(".")[0] == PACKAGE else outside).add(
                        alias.name if alias.name.split(".")[0] == PACKAGE else alias.name.split(".")[0])
        edges[name] = {t for t in found if t in files and t != name}
        externals[name] = outside
    return edges, externals


EDGES, EXTERNALS = _graph()


def _short(module: str) -> str:
    return module[len(PACKAGE) + 1:] if module.startswith(PACKAGE + ".") else module


def _part(module: str) -> str:
    """The part of the core a module belongs to (core.model, core.runs, ...)."""
    return ".".join(_short(module).split(".")[:2])


def test_the_graph_is_read():
    assert len(EDGES) > 40
    assert f"{PACKAGE}.core.model.hysteresis" in EDGES[f"{PACKAGE}.core.control.compensation"]


def test_no_import_cycle():
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in EDGES[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(_short(w))
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in EDGES:
        if v not in index:
            visit(v)
    assert cycles == []


@pytest.mark.parametrize("module", sorted(m for m in EDGES if _short(m).startswith("core")))
def test_the_core_is_ros_free_and_points_one_way(module):
    assert not EXTERNALS[module] & {"rclpy", "std_msgs", "diagnostic_msgs", "rosbags", "matplotlib"}, EXTERNALS[module]
    part = _part(module)
    assert part in MAY_IMPORT or part in SHARED_LEAVES | {"core"}, f"{part}: a part of the core with no rule in MAY_IMPORT"
    for target in EDGES[module]:
        other = _part(target)
        assert _short(target).startswith("core"), f"{_short(module)} imports {_short(target)} from outside the core"
        if other in (part, "core") or other in SHARED_LEAVES:
            continue
        assert other in MAY_IMPORT.get(part, set()), f"{_short(module)} ({part}) imports {_short(target)} ({other})"


@pytest.mark.parametrize("module", sorted(m for m in EDGES if _short(m).split(".")[0] in ("runtime", "backends")))
def test_the_hardware_loop_and_the_backends_are_ros_free(module):
    """The hardware's loop (runtime.hardware_loop) and the backends run without ROS: a DAQ's loop can be tested,
    and a backend written, with no rclpy installed."""
    assert not EXTERNALS[module] & {"rclpy", "std_msgs", "std_srvs", "lifecycle_msgs", "diagnostic_msgs"}, \
        (module, EXTERNALS[module])


def _folder(module: str) -> str:
    """The folder outside the core a module belongs to."""
    return _short(module).split(".")[0]


def test_the_layout_explains_itself():
    """Folders by kind: the top level holds the library face only; nodes/ the nodes (each a ROS process with a
    ``main``); ros/ the ROS plumbing they, the rig client and the tools share; cli/ every other command-line tool
    (each with a ``main``) and what they share."""
    assert {p.name for p in ROOT.glob("*.py")} == TOP_LEVEL
    folders = {p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders == {"core", "io", "runtime", "backends", "ros", "rig", "nodes", "cli"}, folders
    for path in sorted((ROOT / "nodes").glob("*.py")):
        if path.stem == "__init__":
            continue
        text = path.read_text()
        assert "def main(" in text and re.search(r"Node\b", text), path.name
    for path in sorted((ROOT / "cli").glob("*.py")):
        if path.stem not in ("__init__", "tool"):
            assert "def main(" in path.read_text(), path.name
    scripts = re.findall(r'"(valve_\w+) = piezo_valve_ros\.(\w+)\.(\w+):main"', (ROOT.parent / "setup.py").read_text())
    assert len(scripts) >= 11
    for executable, folder, module in scripts:   # a tool is cli/<what follows valve_>.py; a node lives in nodes/
        assert (folder, module) in {("nodes", executable[len("valve_"):]), ("cli", executable[len("valve_"):])} or \
            (folder == "nodes" and executable == "valve_identification" and module == "identification"), executable


@pytest.mark.parametrize("module", sorted(m for m in EDGES if not _short(m).startswith("core") and m != PACKAGE))
def test_each_folder_imports_only_the_layers_below_it(module):
    """Nothing imports a command-line tool but a tool; no library imports a node."""
    folder = _folder(module)
    allowed = FOLDER_MAY_IMPORT[folder] | {folder}
    for target in EDGES[module]:
        other = _folder(target)
        if other == "core" or other == folder:
            continue
        assert other in allowed, \
            f"{_short(module)} ({folder}) imports {_short(target)} ({other})"


def test_every_relative_link_in_the_docs_points_at_a_file():
    import re
    top = ROOT.parent
    broken = []
    for md in [top / "README.md", *sorted((top / "docs").rglob("*.md"))]:
        for m in re.finditer(r"\]\(([^)#\s]+)(#[^)]*)?\)", md.read_text()):
            link = m.group(1)
            if not link.startswith(("http://", "https://", "mailto:")) and not (md.parent / link).exists():
                broken.append(f"{md.relative_to(top)}: {link}")
    assert broken == []


def test_the_loop_nodes_start_without_scipy_signal():
    """scipy.signal's import is most of a node's start-up (0.6 s of CPU); the hardware's and the controller's
    per-sample paths do not need it, so neither importing them nor a few control steps loads it."""
    import subprocess
    import sys
    code = ("import sys\n"
            "import piezo_valve_ros.nodes.hardware, piezo_valve_ros.nodes.controller\n"
            "from piezo_valve_ros.core.sim.simulator import SimulatedValve, ValveSimConfig\n"
            "from piezo_valve_ros.core.control.strategies import ControllerConfig, ValveController, gain_set\n"
            "valve = SimulatedValve(ValveSimConfig())\n"
            "for name in ('pid_hc_5', 'ff_pid_g_2'):\n"
            "    strategy, gains = gain_set(name)\n"
            "    controller = ValveController(ControllerConfig(strategy=strategy, gains=gains))\n"
            "    for _ in range(20):\n"
            "        valve.step(controller.step(10e-6, valve.step(5.0) * 1e-6))\n"
            "print(sorted(m for m in sys.modules if m.startswith('scipy.signal')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def test_the_steady_state_of_a_filter_is_scipys():
    """dynamics.steady_state (the nodes' lfilter_zi without scipy.signal) gives scipy's answer."""
    import numpy as np
    from scipy.signal import lfilter_zi
    from piezo_valve_ros.core.model import PAPER_VALVE_MODEL, first_order_lag, second_order, steady_state
    filters = [first_order_lag(0.01, 1e-4), PAPER_VALVE_MODEL.discretise(1e-4), PAPER_VALVE_MODEL.discretise(1e-3),
               second_order(2 * np.pi * 60, 0.6).discretise(5e-4)]
    for f in filters:
        assert np.allclose(steady_state(f.b, f.a), lfilter_zi(f.b, f.a), rtol=1e-12, atol=1e-12)
    # unnormalised, b shorter than a (as scipy takes them)
    assert np.allclose(steady_state([0.0, 0.4], [2.0, -1.2, 0.2]), lfilter_zi([0.0, 0.4], [2.0, -1.2, 0.2]))


def test_every_typed_error_shares_the_one_base():
    """Each ``...Error`` class the package defines derives from ``core.errors.PiezoValveError`` (besides the
    built-in class it always was), so one ``except`` serves the tools' error handling."""
    from piezo_valve_ros.core import PiezoValveError
    from piezo_valve_ros.cli.tool import run_tool
    errors = {}
    for path in ROOT.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.name.endswith("Error"):
                errors[f"{_module_name(path)}.{node.name}"] = [ast.unparse(b) for b in node.bases]
    assert len(errors) >= 9
    assert not [name for name, bases in errors.items() if "PiezoValveError" not in bases
                and not name.endswith("errors.PiezoValveError")], errors

    def fails():
        raise PiezoValveError("bad input")
    assert run_tool("valve_x", fails) == 2


LIBRARY_PARTS = ("core.model", "core.control", "core.sim", "core.identification", "core.tuning", "core.monitoring")


@pytest.mark.parametrize("part", LIBRARY_PARTS)
def test_each_part_of_the_core_exports_its_everyday_names_lazily(part):
    """``from piezo_valve_ros.core.<part> import <name>`` gives the object its submodule defines, for every name
    the part exports; importing the part alone imports none of its submodules (a node that needs one module of
    a part does not pay for the rest)."""
    import subprocess
    import sys
    package = f"piezo_valve_ros.{part}"
    code = (f"import sys, importlib; m = importlib.import_module({package!r}); "
            f"print(sorted(k for k in sys.modules if k.startswith({package!r} + '.')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert loaded.returncode == 0, loaded.stderr
    assert loaded.stdout.strip() == "[]", loaded.stdout
    import importlib
    module = importlib.import_module(package)
    assert module.__all__
    for name in module.__all__:
        value = getattr(module, name)
        if isinstance(value, type) or callable(value):   # defined in the part (constants: by their submodule)
            assert value.__module__.startswith(package + "."), (name, value.__module__)
    with pytest.raises(AttributeError, match="has no attribute 'no_such_name'"):
        getattr(module, "no_such_name")


def test_a_parameter_spec_checks_type_range_and_choices_with_one_line_naming_it():
    """ParameterSpec.checked: the value as the default's type, within its range or choices; every refusal is one
    line that names the parameter and the value."""
    from piezo_valve_ros.core import ParameterSpec
    clock = ParameterSpec("clock", "realtime", "", choices=("realtime", "lockstep"))
    assert clock.checked("lockstep") == "lockstep"
    batch = ParameterSpec("samples_batch", 1000, "", low=1)
    assert batch.checked(20.0) == 20 and isinstance(batch.checked(20.0), int)
    period = ParameterSpec("period_s", 1.0, "", low=0.0, high=60.0)
    assert period.checked(3) == 3.0
    flag = ParameterSpec("push", True, "")
    refused = [(clock, "wallclock", "clock must be one of realtime, lockstep, got 'wallclock'"),
               (clock, 3, "clock must be a string, got 3"),
               (batch, 0, "samples_batch must be >= 1, got 0"),
               (batch, 2.5, "samples_batch"),
               (period, 61, "period_s must lie in [0, 60], got 61.0"),
               (period, float("nan"), "period_s"),
               (period, "1", "period_s must be a number"),
               (flag, "false", "push must be true or false")]
    for spec, value, message in refused:
        with pytest.raises(ValueError) as info:
            spec.checked(value)
        assert str(info.value).startswith(message) and "\n" not in str(info.value), str(info.value)
    assert "one of realtime, lockstep" in clock.help_line() and clock.range_text() == "realtime or lockstep"


def test_identification_hands_the_controller_typed_values_not_parameter_names():
    """The seam between identification and control is typed (``Effect.compensation`` fills ``CompensationModel``
    fields): no controller parameter name is written in the identification's source; they belong to the node's and
    the files' edge (``CompensationModel.to_parameters``/``from_parameters``)."""
    from piezo_valve_ros.core.control import MODEL_PARAMETERS
    found = []
    for path in (ROOT / "core" / "identification").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in MODEL_PARAMETERS:
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}")
    assert found == []


FACES = ("io", "runtime", "backends", "ros", "rig")   # besides the core's parts and the core itself
CORE_MODULES = ("metrics", "runs", "validation", "defaults", "blas", "errors")   # the core's own: its face's
MAX_DEEP_IMPORTS = 30


def _deep(module: str) -> bool:
    """Whether ``from <module> import`` reaches past a face: into a module of the core's parts or of the folders
    with a face (the nodes and the command-line tools are executables, imported where they are)."""
    parts = module.split(".")
    if parts[0] != PACKAGE or len(parts) < 3:
        return False
    if parts[1] == "core":
        return len(parts) > 3 or parts[2] in CORE_MODULES
    return parts[1] in FACES


def test_tests_and_benches_import_through_the_faces():
    """Tests and benches import what they use from the faces (``piezo_valve_ros.core.identification``, ``...io``),
    as a user does, so a module can move behind its face without touching them; at most MAX_DEEP_IMPORTS reach past
    one (private helpers a test pins down)."""
    deep = []
    for path in sorted(list((ROOT.parent / "test").glob("*.py")) + list((ROOT.parent / "bench").glob("*.py"))):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and _deep(node.module):
                deep.append(f"{path.name}:{node.lineno} {node.module}")
    assert len(deep) <= MAX_DEEP_IMPORTS, "\n".join(deep)


def test_every_effect_has_its_three_homes():
    """Each catalogue effect is named by the identification (its module in ``core/identification/effects``), made by
    stages of the simulated valve (``simulated_by``: StageSwitch names) and compensated by fields of the
    controller's model (``compensated_by``: a control term's, or the GPIM's), or refused with a reason (none
    declared: its ``compensation`` raises NotCompensable).  Every switchable stage of the simulated valve makes an
    effect, except the amplifier's slew limit and the sensor's noise (measured, not named)."""
    check_three_homes()


def check_three_homes() -> None:
    """The three-homes check on the registries as they stand (read from their modules: a test may extend them)."""
    from piezo_valve_ros.core.control import CompensationModel
    from piezo_valve_ros.core.control import terms
    from piezo_valve_ros.core.identification import NotCompensable
    from piezo_valve_ros.core.identification import effects
    from piezo_valve_ros.core.sim import stages as sim_stages
    stages = {s.name for s in sim_stages.STAGE_SWITCHES}
    homes = {t.field for t in terms.TERMS} | {"gpim"}
    assert homes <= {f.name for f in dataclasses.fields(CompensationModel)} | set(CompensationModel().terms)
    for effect in effects.CATALOGUE:
        assert effect.simulated_by and set(effect.simulated_by) <= stages, effect.name
        assert set(effect.compensated_by) <= homes, effect.name
        if not effect.compensated_by:   # the feedback's: it says why
            with pytest.raises(NotCompensable, match=effect.name):
                effect().compensation(None, np.zeros(0))
    assert stages - {s for e in effects.CATALOGUE for s in e.simulated_by} == {"slew_limit", "noise"}


def test_a_term_on_the_spools_path_brings_its_steps_and_every_term_has_a_place():
    """The controller's reference path and ModelValve fold the ``output`` place's terms by their steps: a term there
    without them, or at a place that is none of the chain's, is refused where it is declared."""
    from piezo_valve_ros.core.control import terms
    assert all(t.place in terms.PLACES for t in terms.TERMS)
    assert [t.field for t in terms.TERMS if t.place == "output"] == ["backlash"]
    with pytest.raises(ValueError, match="brings its forward and inverse steps"):
        terms.Term("clearance", {}, dict, lambda get: None, place="output")
    with pytest.raises(ValueError, match="place must be one of"):
        terms.Term("clearance", {}, dict, lambda get: None, place="after G")


def test_the_sim_backends_parameters_are_its_stages_declarations():
    """The ``sim`` backend declares its own two parameters, a switch per ``StageSwitch`` and each stage's settings from
    the stage's module (``StageParameters``, listed in ``STAGE_PARAMETERS``): no name twice, none by hand."""
    import importlib
    from piezo_valve_ros.backends import SimBackend
    from piezo_valve_ros.core.sim import stages
    declared = [p.name for p in SimBackend.PARAMETERS]
    from_stages = [spec.name for stage in stages.STAGE_PARAMETERS for spec in stage.specs]
    assert len(declared) == len(set(declared))
    assert set(declared) == {"seed", "sample_period_s"} | {s.name for s in stages.STAGE_SWITCHES} | set(from_stages)
    for path in (ROOT / "core" / "sim" / "stages").glob("*.py"):
        module = importlib.import_module(f"piezo_valve_ros.core.sim.stages.{path.stem}")
        if isinstance(getattr(module, "PARAMETERS", None), stages.StageParameters):
            assert module.PARAMETERS in stages.STAGE_PARAMETERS, path.stem


def test_an_effect_that_fills_a_field_it_does_not_declare_is_refused():
    """The declaration is what ``to_controller`` holds an effect to: a compensation that fills another field of the
    controller's model is a TypeError naming it, not a silent change of the model."""
    from piezo_valve_ros.core.identification import CATALOGUE
    creep = next(e for e in CATALOGUE if e.name == "creep")
    stray = type("StrayCreep", (creep,), {"compensation": lambda self, model, coefs: {"backlash": None}})
    with pytest.raises(TypeError, match="creep effect's compensation fills backlash, which it does not declare"):
        stray().controller_fields(None, np.zeros(0))


def test_the_simulated_valve_is_its_chain_of_links_folded_over_a_config():
    """Every stage module of the simulated valve has its link in the chain (``stages.CHAIN`` before the spool,
    ``stages.SENSING`` after it), and ``SimulatedValve`` is that fold: a config with every switch on has one stage per
    link and the spool; the ideal valve keeps the amplifier, the hysteresis, G_v and the sensor alone."""
    import importlib
    from piezo_valve_ros.core.sim import SimulatedValve, ValveSimConfig
    from piezo_valve_ros.core.sim.stages import CHAIN, SENSING, STAGE_SWITCHES
    folder = ROOT / "core" / "sim" / "stages"
    modules = [p.stem for p in folder.glob("*.py") if p.stem not in ("__init__", "base")]
    assert len(modules) >= 9, modules
    links = {id(link) for link in CHAIN + SENSING}
    for name in modules:
        module = importlib.import_module(f"piezo_valve_ros.core.sim.stages.{name}")
        assert any(id(v) in links for k, v in vars(module).items() if k.endswith("LINK")), name
    every = ValveSimConfig(sensor=dataclasses.replace(ValveSimConfig().sensor, delay_samples=2))
    for switch in STAGE_SWITCHES:
        every = switch.set(every, True)
    assert len(SimulatedValve(every)._stages) == len(CHAIN) + 1 + len(SENSING)
    kinds = [type(s).__name__ for s in SimulatedValve(ValveSimConfig().ideal())._stages]
    assert kinds == ["Amplifier", "Hysteresis", "Dynamics", "_Spool", "Sensor"], kinds
