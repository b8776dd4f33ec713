"""
The package as a ROS 2 Jazzy user gets it: `colcon build`, then `ros2 run softshape_ros <node>`.

Builds into a temporary prefix, finds each node executable the way `ros2 run` does (ament
index prefix + lib/softshape_ros/<exe>), starts it from outside the source tree, waits for
it in the ROS graph, and checks that SIGINT ends it with exit code 0.
"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import setuptools

ROOT = Path(__file__).resolve().parent.parent
PKG = 'softshape_ros'


def setup_py_entry_points() -> dict:
    """Run setup.py with setuptools.setup captured: {executable: target}."""
    captured = {}
    real = setuptools.setup
    setuptools.setup = lambda **kw: captured.update(kw)
    cwd = os.getcwd()
    try:
        os.chdir(ROOT)
        code = compile((ROOT / 'setup.py').read_text(), str(ROOT / 'setup.py'), 'exec')
        exec(code, {'__file__': str(ROOT / 'setup.py'), '__name__': '__main__'})
    finally:
        os.chdir(cwd)
        setuptools.setup = real
    scripts = captured['entry_points']['console_scripts']
    return dict(s.replace(' ', '').split('=', 1) for s in scripts)


ENTRY_POINTS = setup_py_entry_points()
NODES = sorted(n for n, target in ENTRY_POINTS.items() if '.nodes.' in target)

# Arguments a node needs to start on a machine with no rig, from the test's fixtures
# (e.g. a model file); by default a node must start with no arguments.
NODE_ARGS = {
    'inference': lambda request: ['--ros-args', '-p',
                                  f'model:={request.getfixturevalue("trained_checkpoint")}'],
    'shape_controller': lambda request: [
        '--ros-args', '-p', f'model:={request.getfixturevalue("trained_checkpoint")}'],
}


@pytest.fixture(scope='session')
def colcon_install(tmp_path_factory):
    """`colcon build` of this package into a fresh prefix; returns the install path."""
    base = tmp_path_factory.mktemp('colcon')
    colcon = Path(sys.executable).parent / 'colcon'
    assert colcon.exists(), f'colcon not found next to {sys.executable}'
    proc = subprocess.run(
        [str(colcon), '--log-base', str(base / 'log'), 'build', '--base-paths', str(ROOT),
         '--build-base', str(base / 'build'), '--install-base', str(base / 'install'),
         '--event-handlers', 'console_direct-'],
        cwd=base, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    return base / 'install'


def ros2_run_lookup(install: Path, executable: str) -> Path:
    """Resolve an executable like `ros2 run` (ament index -> prefix/lib/<pkg>/<exe>)."""
    from ament_index_python.packages import get_package_prefix
    old = os.environ.get('AMENT_PREFIX_PATH')
    os.environ['AMENT_PREFIX_PATH'] = str(install / PKG)
    try:
        prefix = Path(get_package_prefix(PKG))
    finally:
        if old is None:
            del os.environ['AMENT_PREFIX_PATH']
        else:
            os.environ['AMENT_PREFIX_PATH'] = old
    path = prefix / 'lib' / PKG / executable
    assert path.is_file(), f'{executable}: not at {path}'
    assert os.access(path, os.X_OK), f'{path}: not executable'
    return path


def install_env(install: Path) -> dict:
    """Build the environment sourcing install/setup.bash gives, plus localhost DDS."""
    env = dict(os.environ)
    prefix = install / PKG
    site = next(prefix.glob('lib/python3*/site-packages'))
    env['AMENT_PREFIX_PATH'] = str(prefix)
    env['PYTHONPATH'] = str(site)
    env['PYTHONUNBUFFERED'] = '1'
    return env


def test_colcon_installs_package_resources(colcon_install):
    share = colcon_install / PKG / 'share' / PKG
    assert (share / 'package.xml').is_file()
    assert (share / 'config' / 'rig.yaml').is_file()
    index = colcon_install / PKG / 'share' / 'ament_index' / 'resource_index' / 'packages' / PKG
    assert index.is_file()
    assert ros2_run_lookup(colcon_install, 'softshape').is_file()


def test_installed_cli_reads_installed_config(colcon_install, tmp_path):
    exe = ros2_run_lookup(colcon_install, 'softshape')
    proc = subprocess.run([str(exe), 'config'], cwd=tmp_path, env=install_env(colcon_install),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert '"seg2_ch3"' in proc.stdout


@pytest.mark.ros
@pytest.mark.parametrize('executable', NODES)
def test_node_starts_in_graph_and_exits_zero_on_sigint(executable, colcon_install, tmp_path,
                                                       rclpy_session, request):
    exe = ros2_run_lookup(colcon_install, executable)
    args = NODE_ARGS[executable](request) if executable in NODE_ARGS else []
    proc = subprocess.Popen([str(exe)] + args, cwd=tmp_path,
                            env=install_env(colcon_install), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    probe = rclpy_session.create_node(f'probe_{executable}')
    try:
        deadline = time.monotonic() + 60
        seen = False
        while time.monotonic() < deadline and proc.poll() is None:
            if executable in probe.get_node_names():
                seen = True
                break
            time.sleep(0.1)
        assert seen, f'{executable} never joined the graph (exit {proc.poll()}):\n' + (
            proc.stdout.read() if proc.poll() is not None else '')
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, f'{executable} exited {proc.returncode}:\n{out}'
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
        probe.destroy_node()


def test_every_node_module_is_an_entry_point():
    modules = sorted(p.stem for p in (ROOT / PKG / 'nodes').glob('*.py')
                     if not p.name.startswith('_') and p.stem != 'common')
    assert modules == NODES


def launch_nodes(path: Path):
    """(exec, name, [params-file templates], {param: value}) for each <node> of an XML launch."""
    import xml.etree.ElementTree as ET
    root = ET.parse(path).getroot()
    assert root.tag == 'launch', path
    for node in root.iter('node'):
        files = [p.get('from') for p in node.findall('param') if p.get('from')]
        values = {p.get('name'): p.get('value') for p in node.findall('param') if p.get('name')}
        yield node.get('pkg'), node.get('exec'), node.get('name'), files, values


LAUNCH_FILES = sorted((ROOT / 'launch').glob('*.launch.xml'))


@pytest.mark.parametrize('launch', LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_only_installed_executables_and_parameter_files(launch, colcon_install):
    import yaml
    share = colcon_install / PKG / 'share' / PKG
    assert (share / 'launch' / launch.name).is_file(), f'{launch.name} is not installed'
    nodes = list(launch_nodes(launch))
    assert nodes, f'{launch.name} starts no node'
    for pkg, exe, name, files, values in nodes:
        assert pkg == PKG
        ros2_run_lookup(colcon_install, exe)
        assert files, f'{launch.name}: {name} has no parameter file'
        declared = set()
        for f in files:
            path = Path(f.replace('$(find-pkg-share softshape_ros)', str(share)))
            assert path.is_file(), f'{launch.name}: {name}: {path} is not installed'
            (params,) = yaml.safe_load(path.read_text()).values()
            declared |= set(params['ros__parameters'])
        unknown = set(values) - declared
        assert not unknown, (f'{launch.name}: {name} sets {sorted(unknown)}, which its '
                             f'parameter file does not declare')


def test_readme_node_table_matches_nodes_and_parameter_files():
    import re
    import yaml
    text = (ROOT / 'README.md').read_text()
    table = text[text.index('<!-- nodes-table'):]
    table = table[:table.index('\n\n')]
    rows = {}
    for line in table.splitlines()[1:]:
        cells = [c.strip() for c in line.strip('|').split('|')]
        rows[cells[0].split()[0]] = cells[-1]
    assert sorted(rows) == NODES, 'README nodes table and softshape_ros/nodes/ differ'
    for node, params_cell in rows.items():
        (params,) = yaml.safe_load(
            (ROOT / 'config' / 'params' / f'{node}.yaml').read_text()).values()
        declared = set(params['ros__parameters'])
        source = (ROOT / PKG / 'nodes' / f'{node}.py').read_text()
        listed = re.sub(r'\([^)]*\)', '', params_cell)           # drop explanations
        for name in re.findall(r'(?:^|, )([a-z][a-z0-9_]+)', listed):
            assert name in declared or f"'{name}'" in source, (
                f'README lists parameter {name!r} of {node}, which it does not declare')
