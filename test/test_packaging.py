"""What a ROS install sees: the launch file starts the nodes valve_rig starts, from the same parameters, and
every node has its console script.  Read from the files (no `launch` package here: the launch file is parsed,
not run)."""
import ast
from pathlib import Path

import yaml

from piezo_valve_ros.cli.rig import parse_args, rig_parameters
from piezo_valve_ros.runtime import NODE_MODULES

ROOT = Path(__file__).resolve().parent.parent


def _launch_nodes() -> dict[str, dict]:
    """executable -> {"condition": (If/Unless, launch argument), "parameters": source names} of each Node(...)."""
    tree = ast.parse((ROOT / "launch" / "rig.launch.py").read_text())
    nodes = {}
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Node":
            kw = {k.arg: k.value for k in call.keywords}
            condition = None
            if "condition" in kw:
                c = kw["condition"]
                arg = c.args[0]
                name = arg.args[0].value if isinstance(arg, ast.Call) else arg.id
                condition = (c.func.id, name)
            params = [p.id if isinstance(p, ast.Name) else "dict" for p in kw["parameters"].elts]
            nodes[kw["executable"].value] = {"condition": condition, "parameters": params}
    return nodes


def test_the_launch_file_starts_the_nodes_valve_rig_starts_from_the_same_parameters():
    nodes = _launch_nodes()
    assert set(nodes) == set(NODE_MODULES)          # every node valve_rig can start, and no other
    assert nodes["valve_hardware"]["condition"] == ("UnlessCondition", "composed")
    assert nodes["valve_controller"]["condition"] == ("UnlessCondition", "composed")
    assert nodes["valve_composed"]["condition"] == ("IfCondition", "composed")
    options = vars(parse_args([]))
    for executable, launch_arg in (("valve_identification", "identify"), ("valve_monitor", "monitor")):
        assert nodes[executable]["condition"] == ("IfCondition", launch_arg)
        assert launch_arg in options                # valve_rig --identify / --monitor start the same
    assert "composed" in options
    assert all(n["parameters"][0] == "params" for n in nodes.values())   # one parameters file for all


def test_the_launch_files_default_parameters_are_valve_rigs_defaults():
    """config/rig.yaml (the launch file's default) gives each node what valve_rig gives it by default."""
    config = yaml.safe_load((ROOT / "config" / "rig.yaml").read_text())
    hw, ctl = rig_parameters(parse_args([]))
    for section, rig in (("/**/valve_hardware", hw), ("/**/valve_controller", ctl)):
        file_values = config[section]["ros__parameters"]
        shared = set(file_values) & set(rig) - {"lockstep.step_budget", "realtime.busy_poll_s"}
        assert shared, section
        assert {k: file_values[k] for k in shared} == {k: rig[k] for k in shared}, section


def test_every_node_has_a_console_script_and_an_install_path():
    setup = (ROOT / "setup.py").read_text()
    for executable, module in NODE_MODULES.items():
        assert f'"{executable} = piezo_valve_ros.nodes.{module}:main"' in setup, executable
    for installed in ('"/config", glob("config/*.yaml")', '"/launch", glob("launch/*.launch.py")',
                      '["resource/" + package_name]', '["package.xml"]'):
        assert installed in setup, installed
    assert (ROOT / "resource" / "piezo_valve_ros").exists()


def test_the_report_page_is_written_from_the_typed_definition_and_a_bad_report_is_caught():
    import subprocess
    import sys
    from piezo_valve_ros.core.identification import check_report
    check = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_schema.py"), "--check"],
                           capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr
    problems = check_report({"range_um": "wide", "extra": 1})
    assert "report: extra is not in the schema" in problems and "report.range_um: str, expected float" in problems
    assert "report: baseline missing" in problems


def test_the_report_digest_writes_each_records_report_without_its_seconds(tmp_path):
    """``scripts/report_digest.py`` (the A/B of a change's reports): on one of the records others made it writes that
    record's report, less its ``seconds``, valid against the schema, and prints its digest and effects."""
    import json
    import subprocess
    import sys
    from piezo_valve_ros.core.identification import check_report
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "report_digest.py"), str(tmp_path),
                           "external: thermal drift"], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    [written] = list(tmp_path.glob("*.json"))
    report = json.loads(written.read_text())
    assert "seconds" not in report and report["effects_added"] == ["drift"]
    assert check_report({**report, "seconds": 0.0}) == []
    assert done.stdout.startswith("external: thermal drift") and done.stdout.rstrip().endswith("drift")


def test_package_xml_declares_what_the_code_imports_through_keys_rosdep_resolves():
    """Every third-party import of the package is declared: by a rosdep key in package.xml, or (rosbags,
    threadpoolctl: no rosdep key; numba: none for Ubuntu after focal) by setup.py's install_requires and named in the
    package.xml's comment."""
    import xml.dom.minidom
    doc = xml.dom.minidom.parse(str(ROOT / "package.xml"))
    keys = {e.firstChild.data for tag in ("exec_depend", "depend") for e in doc.getElementsByTagName(tag)}
    assert {"rclpy", "std_msgs", "diagnostic_msgs", "rcl_interfaces", "python3-numpy", "python3-scipy",
            "python3-yaml"} <= keys
    assert not keys & {"rosbags", "python3-threadpoolctl", "python3-numba"}   # unresolvable: rosdep would fail
    text = (ROOT / "package.xml").read_text()
    setup = (ROOT / "setup.py").read_text()
    for pip_only in ("rosbags", "threadpoolctl", "numba"):
        assert pip_only in text and f'"{pip_only}' in setup, pip_only


def test_the_venvs_packages_are_compiled_to_bytecode():
    """scripts/setup_venv.sh installs the packages compiled (uv's --compile-bytecode, pip's default): a node or tool
    started where bytecode may not be written (PYTHONDONTWRITEBYTECODE) would compile every module it imports,
    at every start.  Checked on the modules every node imports, in the venv these tests run in."""
    import importlib
    import importlib.util
    import os
    import sys
    if sys.prefix == sys.base_prefix:
        import pytest
        pytest.skip("not run from a venv: scripts/setup_venv.sh made none of these packages")
    for name in ("numpy", "numpy.linalg._linalg", "scipy.signal", "rclpy.node", "rosbags.rosbag2", "yaml"):
        source = importlib.util.find_spec(name).origin
        assert os.path.exists(importlib.util.cache_from_source(source)), f"{name}: {source} has no bytecode"


def test_colcon_builds_the_package_as_a_ros_workspace_does(tmp_path):
    """``colcon build`` (colcon from pip, as on a Jazzy machine) of the package copied into a fresh workspace's src:
    the install space has every node's executable in lib/piezo_valve_ros (where ``ros2 run`` looks), the ament
    index marker (``ros2 pkg list``), package.xml, the launch file and the configs in share/, and the installed
    ``valve_rig --help`` runs after ``source install/setup.bash`` (from the install space, not this checkout)."""
    import os
    import shutil
    import subprocess
    import sys
    colcon = shutil.which("colcon", path=str(Path(sys.executable).parent))
    assert colcon, "colcon is in requirements.txt: scripts/setup_venv.sh installs it into the venv"
    source = tmp_path / "src" / "piezo_valve_ros"
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".git", ".venv*", "build", "install", "log",
                                                                "__pycache__", "*.egg-info", ".pytest_cache"))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "AMENT_PREFIX_PATH")}
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    built = subprocess.run([colcon, "build", "--base-paths", "src", "--event-handlers", "console_direct-"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, timeout=240)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    prefix = tmp_path / "install" / "piezo_valve_ros"
    installed = {p.name for p in (prefix / "lib" / "piezo_valve_ros").iterdir()}
    assert set(NODE_MODULES) | {"valve_rig", "valve_identify", "valve_command", "valve_plot"} <= installed, installed
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "piezo_valve_ros").is_file()
    assert (share / "piezo_valve_ros" / "package.xml").is_file()
    assert (share / "piezo_valve_ros" / "launch" / "rig.launch.py").is_file()
    assert {p.name for p in (share / "piezo_valve_ros" / "config").iterdir()} == \
        {p.name for p in (ROOT / "config").glob("*.yaml")}
    run = subprocess.run(["bash", "-c", "source install/setup.bash && cd / && valve_rig --help && python -c "
                          "'import piezo_valve_ros, sys; print(piezo_valve_ros.__file__)'"],
                         cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert "usage: valve_rig" in run.stdout
    assert run.stdout.strip().splitlines()[-1].startswith(str(prefix))   # the installed package, not this checkout


def test_a_timing_page_gives_the_hosts_yardstick_and_other_pages_do_not(tmp_path):
    """bench/harness.Lines: a timing bench's page says the host's speed as the bench started and ended (this shared
    machine's seconds drift by a fifth within a day: two pages compare only as far as their yardsticks agree); a
    page of other figures does not."""
    from harness import Lines, host_yardstick

    speed = host_yardstick()
    assert speed.python_us > 0 and speed.gram_ms > 0
    timing, plain = Lines(timing=True), Lines()
    for lines, name in ((timing, "timing.md"), (plain, "plain.md")):
        lines("a figure 1.00 s")
        lines.write_markdown(str(tmp_path / name), "bench/x.py")
    page = (tmp_path / "timing.md").read_text()
    assert page.count("Host yardstick") == 1 and "at the start sum(range(1000))" in page and "at the end " in page
    assert "Gram product" in page and "a figure 1.00 s" in page
    assert "Host yardstick" not in (tmp_path / "plain.md").read_text() and "a figure" in (tmp_path / "plain.md").read_text()
