"""
The package as a ROS 2 Jazzy user gets it: `colcon build`, then `ros2 run softshape_ros <node>`.

Builds into a temporary prefix, finds each node executable the way `ros2 run` does (ament
index prefix + lib/softshape_ros/<exe>), starts it from outside the source tree, waits for
it to answer in the ROS graph, and checks that SIGINT ends it with exit code 0.
"""

import os
import shutil
import signal
import subprocess
import sys
from dataclasses import dataclass
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


def colcon_command() -> list:
    """
    Return how to run colcon with the interpreter running the tests.

    ``python -m colcon`` where colcon-core imports (this machine's .venv, or a Jazzy host's
    ``--system-site-packages`` venv): the executables it installs then get this Python in
    their shebang, as ROS 2's docs ask for venvs. Otherwise the ``colcon`` on PATH.
    """
    import importlib.util
    import shutil
    if importlib.util.find_spec('colcon') and importlib.util.find_spec('colcon_core'):
        return [sys.executable, '-m', 'colcon']
    found = shutil.which('colcon')
    assert found, (f'colcon not found: neither importable by {sys.executable} nor on PATH '
                   '(apt install python3-colcon-common-extensions)')
    return [found]


@pytest.fixture(scope='session')
def colcon_workspace(tmp_path_factory):
    """`colcon build` of this package in a fresh workspace; returns its folder."""
    base = tmp_path_factory.mktemp('colcon')
    proc = subprocess.run(
        colcon_command() + ['--log-base', str(base / 'log'), 'build', '--base-paths', str(ROOT),
                            '--build-base', str(base / 'build'),
                            '--install-base', str(base / 'install'),
                            '--event-handlers', 'console_direct-'],
        cwd=base, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'
    share_compiled_kernels(base / 'install')
    return base


def share_compiled_kernels(install: Path) -> None:
    """
    Give the installed modules the simulator kernels numba compiled for the source tree.

    What `python -m softshape_ros.sim.warmup` does once on a host (the README's Jazzy
    steps), done here by copying: `make build` compiled them beside the sources, and the
    install's fresh copy would otherwise compile them again in the first process that
    simulates (30-45 s of the mock hardware node's start). numba's index keys on its
    source's mtime and size, and the build copies a source's mtime in whole seconds, so the
    copy gets the exact one. A module whose installed copy differs keeps no cache.
    """
    site = next((install / PKG).glob('lib/python3*/site-packages')) / PKG
    for nbi in (ROOT / PKG).rglob('__pycache__/*.nbi'):
        module = nbi.name.split('.', 1)[0]
        source = nbi.parent.parent / f'{module}.py'
        installed = site / source.relative_to(ROOT / PKG)
        if not installed.is_file() or installed.read_bytes() != source.read_bytes():
            continue
        st = source.stat()
        os.utime(installed, ns=(st.st_atime_ns, st.st_mtime_ns))
        cache = installed.parent / '__pycache__'
        cache.mkdir(exist_ok=True)
        for f in nbi.parent.glob(nbi.name[:-len('.nbi')] + '*'):    # the index, its code
            shutil.copy2(f, cache / f.name)


@pytest.fixture(scope='session')
def colcon_install(colcon_workspace):
    """Return the install prefix of the colcon-built package."""
    return colcon_workspace / 'install'


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


#: What the `colcon test` check runs: core and ROS tests, small enough for one minute.
COLCON_TEST_SELECTION = ['test/test_session.py', 'test/test_camera_info.py',
                         'test/test_collector.py::test_no_session_waits_idle']


@pytest.mark.ros
def test_colcon_test_runs_the_tests_in_a_workspace(colcon_workspace):
    """`colcon test` + `colcon test-result` as on a Jazzy host: pytest.ini must work there."""
    import xml.etree.ElementTree as ET
    base = colcon_workspace
    results = base / 'test_results'
    common = ['--base-paths', str(ROOT), '--build-base', str(base / 'build'),
              '--install-base', str(base / 'install')]
    proc = subprocess.run(
        colcon_command() + ['--log-base', str(base / 'log'), 'test'] + common
        + ['--test-result-base', str(results), '--event-handlers', 'console_direct-',
           '--pytest-args'] + COLCON_TEST_SELECTION,
        cwd=base, capture_output=True, text=True, timeout=600)
    out = f'{proc.stdout}\n{proc.stderr}'
    assert proc.returncode == 0, f'colcon test failed:\n{out}'
    suite = ET.parse(next(results.rglob('pytest.xml'))).getroot()
    suite = suite if suite.tag == 'testsuite' else suite.find('testsuite')
    counts = {k: int(suite.get(k)) for k in ('tests', 'failures', 'errors')}
    assert counts['tests'] >= 8 and counts['failures'] == counts['errors'] == 0, (counts, out)
    names = {c.get('name') for c in suite.iter('testcase')}
    assert 'test_no_session_waits_idle' in names and 'pytest.missing_result' not in names
    summary = subprocess.run(
        colcon_command() + ['--log-base', str(base / 'log'), 'test-result',
                            '--test-result-base', str(results), '--verbose'],
        cwd=base, capture_output=True, text=True, timeout=120)
    assert summary.returncode == 0, summary.stdout + summary.stderr
    assert '0 errors, 0 failures' in summary.stdout, summary.stdout


def test_installed_cli_reads_installed_config(colcon_install, tmp_path):
    exe = ros2_run_lookup(colcon_install, 'softshape')
    proc = subprocess.run([str(exe), 'config'], cwd=tmp_path, env=install_env(colcon_install),
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert '"seg2_ch3"' in proc.stdout


@pytest.mark.ros
@pytest.mark.parametrize('executable', NODES)
def test_node_starts_in_graph_and_exits_zero_on_sigint(executable, colcon_install, tmp_path,
                                                       ros, request):
    """
    SIGINT once the node spins (it answers a parameter service): the shutdown path, exit 0.

    Its name in the graph alone proves nothing: a node of that name that a process before
    this one ran can linger there (its participant's lease not yet expired), and a SIGINT
    sent on the strength of that met the node still importing.
    """
    from rcl_interfaces.srv import ListParameters

    from waits import round_trip
    exe = ros2_run_lookup(colcon_install, executable)
    args = NODE_ARGS[executable](request) if executable in NODE_ARGS else []
    proc = subprocess.Popen([str(exe)] + args, cwd=tmp_path,
                            env=install_env(colcon_install), stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    probe = ros.node(f'probe_{executable}')
    client = probe.create_client(ListParameters, f'/{executable}/list_parameters')
    answers = []
    try:
        ros.wait_for(lambda: executable in probe.get_node_names() or proc.poll() is not None,
                     60, what=f'{executable} in the graph')
        # a request sent before the node's service matched our client is never answered
        round_trip(ros, lambda k: answers.append(client.call_async(ListParameters.Request())),
                   lambda: any(f.done() for f in answers) or proc.poll() is not None,
                   f'{executable} answering list_parameters')
        assert proc.poll() is None, f'{executable} exited {proc.poll()}:\n{proc.stdout.read()}'
        assert any(f.done() and f.result().result.names for f in answers)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
        assert proc.returncode == 0, f'{executable} exited {proc.returncode}:\n{out}'
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


#: Modules in nodes/ that every node shares; all others are nodes.
NODE_HELPERS = {'common', 'clocks', 'diagnostics', 'parameters'}


def test_every_node_module_is_an_entry_point():
    modules = sorted(p.stem for p in (ROOT / PKG / 'nodes').glob('*.py')
                     if not p.name.startswith('_') and p.stem not in NODE_HELPERS)
    assert modules == NODES


@dataclass
class LaunchedNode:
    """One node a launch file starts, as far as reading the file tells."""

    pkg: str
    exe: str
    name: str
    param_files: list              # parameter file paths, with $(find-pkg-share ...) kept
    values: dict                   # parameters set in the launch file
    args: list                     # command-line arguments
    lifecycle: bool = False


def _xml_nodes(path: Path):
    import xml.etree.ElementTree as ET
    root = ET.parse(path).getroot()
    assert root.tag == 'launch', path
    for node in root.iter('node'):
        files = [p.get('from') for p in node.findall('param') if p.get('from')]
        values = {p.get('name'): p.get('value') for p in node.findall('param') if p.get('name')}
        yield LaunchedNode(node.get('pkg'), node.get('exec'), node.get('name'), files, values,
                           (node.get('args') or '').split())


def _call_name(call) -> str:
    import ast
    f = call.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ''


def _py_nodes(path: Path):
    """Read Node/LifecycleNode calls of a Python launch file (no launch_ros needed)."""
    import ast
    tree = ast.parse(path.read_text())
    for call in ast.walk(tree):
        if not isinstance(call, ast.Call) or _call_name(call) not in ('Node', 'LifecycleNode'):
            continue
        kw = {k.arg: k.value for k in call.keywords}
        const = {k: v.value for k, v in kw.items() if isinstance(v, ast.Constant)}
        files, values = [], {}
        for item in getattr(kw.get('parameters'), 'elts', []):
            if isinstance(item, ast.Call) and _call_name(item) == 'params_file':
                files.append('$(find-pkg-share softshape_ros)/config/params/'
                             f'{item.args[0].value}.yaml')
            elif isinstance(item, ast.Dict):
                values.update({k.value: ast.unparse(v) for k, v in zip(item.keys, item.values)})
        args = [a.value for a in getattr(kw.get('arguments'), 'elts', [])]
        yield LaunchedNode(const['package'], const['executable'], const.get('name'), files,
                           values, args, lifecycle=_call_name(call) == 'LifecycleNode')


def launch_nodes(path: Path) -> list:
    """Return every node an XML or Python launch file starts."""
    return list(_xml_nodes(path) if path.suffix == '.xml' else _py_nodes(path))


LAUNCH_FILES = sorted((ROOT / 'launch').glob('*.launch.*'))


@pytest.mark.parametrize('launch', LAUNCH_FILES, ids=lambda p: p.name)
def test_launch_file_names_only_installed_executables_and_parameter_files(launch, colcon_install):
    import yaml
    share = colcon_install / PKG / 'share' / PKG
    assert (share / 'launch' / launch.name).is_file(), f'{launch.name} is not installed'
    nodes = launch_nodes(launch)
    assert any(n.pkg == PKG for n in nodes), f'{launch.name} starts no node of ours'
    for n in nodes:
        if n.pkg == 'tf2_ros':                   # checked against rig.yaml below
            assert n.exe == 'static_transform_publisher'
            continue
        assert n.pkg == PKG
        ros2_run_lookup(colcon_install, n.exe)
        assert n.param_files, f'{launch.name}: {n.name} has no parameter file'
        declared = set()
        for f in n.param_files:
            path = Path(f.replace('$(find-pkg-share softshape_ros)', str(share)))
            assert path.is_file(), f'{launch.name}: {n.name}: {path} is not installed'
            (params,) = yaml.safe_load(path.read_text()).values()
            declared |= set(params['ros__parameters'])
        unknown = set(n.values) - declared
        assert not unknown, (f'{launch.name}: {n.name} sets {sorted(unknown)}, which its '
                             f'parameter file does not declare')


def _parse_tf_args(args: list) -> dict:
    it = iter(args)
    return {a.lstrip('-'): next(it) for a in it}


@pytest.mark.parametrize('launch', [p for p in LAUNCH_FILES if 'rig' in p.name],
                         ids=lambda p: p.name)
def test_rig_launch_files_publish_the_camera_poses_of_rig_yaml(launch):
    import numpy as np

    from softshape_ros.config import load_rig_config
    from softshape_ros.frames import camera_transforms
    published = {}
    for n in launch_nodes(launch):
        if n.exe == 'static_transform_publisher':
            a = _parse_tf_args(n.args)
            published[a['child-frame-id']] = a
    expected = camera_transforms(load_rig_config())
    assert sorted(published) == sorted(tf.child for tf in expected), launch.name
    for tf in expected:
        a = published[tf.child]
        assert a['frame-id'] == tf.parent
        got_t = [float(a[k]) for k in ('x', 'y', 'z')]
        got_q = np.array([float(a[k]) for k in ('qx', 'qy', 'qz', 'qw')])
        assert np.allclose(got_t, tf.translation, atol=1e-6), (tf.child, got_t)
        # q and -q are one rotation
        assert min(np.abs(got_q - tf.rotation).max(), np.abs(got_q + tf.rotation).max()) < 1e-6


def test_physical_rig_launch_configures_then_activates_the_bridge():
    """The bridge is a LifecycleNode; configure at start, activate once inactive."""
    import ast
    path = ROOT / 'launch' / 'physical_rig.launch.py'
    (bridge,) = [n for n in launch_nodes(path) if n.exe == 'pressure_bridge']
    assert bridge.lifecycle
    tree = ast.parse(path.read_text())
    changes = {}                                # transition -> the node variable it targets
    for call in ast.walk(tree):
        if isinstance(call, ast.Call) and _call_name(call) == 'ChangeState':
            kw = {k.arg: k.value for k in call.keywords}
            target = kw['lifecycle_node_matcher'].args[0].id
            changes[kw['transition_id'].attr] = target
    assert set(changes) == {'TRANSITION_CONFIGURE', 'TRANSITION_ACTIVATE'}
    (variable,) = set(changes.values())
    assigned = [a for a in ast.walk(tree) if isinstance(a, ast.Assign)
                and getattr(a.targets[0], 'id', '') == variable]
    assert _call_name(assigned[0].value) == 'LifecycleNode'
    handlers = [c for c in ast.walk(tree) if isinstance(c, ast.Call)
                and _call_name(c) == 'OnStateTransition']
    (handler,) = handlers
    kw = {k.arg: k.value for k in handler.keywords}
    assert kw['goal_state'].value == 'inactive'
    assert 'TRANSITION_ACTIVATE' in ast.unparse(kw['entities'])


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


#: rosdep keys of ros/rosdistro rosdep/python.yaml this package uses (checked there by hand;
#: python3-safetensors-pip and python3-mcap-pip are not keys).
ROSDEP_PYTHON_KEYS = {
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'cv2': 'python3-opencv',
    'serial': 'python3-serial', 'yaml': 'python3-yaml', 'ruamel': 'python3-ruamel.yaml',
    'tqdm': 'python3-tqdm', 'matplotlib': 'python3-matplotlib', 'torch': 'python3-torch',
    'rosbags': 'python3-rosbags-pip', 'onnxruntime': 'python3-onnxruntime-pip',
    'pytest': 'python3-pytest', 'hypothesis': 'python3-hypothesis',
    'mcap': 'mcap-ros2-support', 'mcap_ros2': 'mcap-ros2-support', 'numba': 'python3-numba',
}
#: Imports with no rosdep key: pip-only, listed in requirements-jazzy.txt.
PIP_ONLY = {'safetensors': 'safetensors', 'onnx': 'onnx', 'onnxscript': 'onnxscript',
            'lz4': 'lz4'}
#: ROS 2 packages imported as Python modules (keys of the Jazzy distribution).
ROS_PACKAGES = {'rclpy', 'rcl_interfaces', 'lifecycle_msgs', 'std_msgs', 'sensor_msgs',
                'diagnostic_msgs', 'diagnostic_updater', 'std_srvs', 'builtin_interfaces',
                'ament_index_python', 'rosgraph_msgs', 'launch', 'launch_ros', 'ament_flake8',
                'ament_pep257', 'geometry_msgs', 'nav_msgs'}


def _imports(paths) -> set:
    import ast
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                found |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split('.')[0])
    return found - set(sys.stdlib_module_names)


def _depends(kinds) -> set:
    import xml.etree.ElementTree as ET
    root = ET.parse(ROOT / 'package.xml').getroot()
    return {e.text.strip() for kind in kinds for e in root.iter(kind)}


def test_every_import_is_declared_for_rosdep_or_the_jazzy_venv():
    import re
    pip = {re.split(r'[<>=\s#]', line.strip())[0].lower()
           for line in (ROOT / 'requirements-jazzy.txt').read_text().splitlines()
           if line.strip() and not line.startswith('#')}
    exec_deps = _depends(['exec_depend', 'depend'])
    test_deps = exec_deps | _depends(['test_depend'])
    launch_deps = exec_deps
    local = {PKG, 'conftest', 'inference_fixtures'} | {
        p.stem for p in (ROOT / 'test').glob('*.py')}
    for paths, declared, what in [
            (list((ROOT / PKG).rglob('*.py')), exec_deps, 'exec_depend'),
            (list((ROOT / 'test').glob('*.py')), test_deps, 'test_depend'),
            (list((ROOT / 'launch').glob('*.py')), launch_deps, 'exec_depend')]:
        for module in sorted(_imports(paths) - local - {'setuptools'}):
            if module in PIP_ONLY:
                assert PIP_ONLY[module] in pip, f'{module}: not in requirements-jazzy.txt'
            elif module in ROSDEP_PYTHON_KEYS:
                key = ROSDEP_PYTHON_KEYS[module]
                assert key in declared, f'{module}: {key} is not a {what} in package.xml'
            else:
                assert module in ROS_PACKAGES, (f'{module} is imported but neither a rosdep '
                                                'key nor a pip-only package is known for it')
                ros_pkg = {'launch': 'launch_ros'}.get(module, module)
                assert ros_pkg in declared, f'{module}: not a {what} in package.xml'
    keys = _depends(['exec_depend', 'test_depend'])
    assert not keys & {'python3-safetensors-pip', 'python3-mcap-pip'}   # no such rosdep keys
    python_keys = {k for k in keys if k.startswith('python3-') or k.endswith('-support')}
    assert python_keys <= set(ROSDEP_PYTHON_KEYS.values()) | {
        'python3-pytest-timeout', 'python3-colcon-common-extensions'}, python_keys


def test_nodes_report_through_their_logger_not_print():
    """Errors reach /rosout and the launch log only through the node's logger."""
    import ast
    for path in sorted((ROOT / PKG / 'nodes').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            assert not (isinstance(node, ast.Call) and getattr(node.func, 'id', '') == 'print'), (
                f'{path.name}:{node.lineno}: print() in a node; use self.get_logger()')
