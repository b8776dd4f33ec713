"""
The package's layers, checked from its source: who may import whom, and no import cycles.

The floor (config.py, scene.py, pressure.py, transport.py) imports no other part of the
package; the core (sim/ hardware/ vision/ data/ model/ control/) imports the floor and each other
without cycles and never rclpy or the application layer (nodes/, commands/, demo/, cli.py,
processes.py); model/ and sim/ do not import each other (experiments that need both live a
floor above them); only the application layer drives hardware/. Imports inside functions
count: a lazy import hides a cycle, it does not remove it.
"""

import ast
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

PKG = Path(__file__).resolve().parent.parent / 'softshape_ros'
FLOOR = {'config', 'scene', 'pressure', 'transport'}
CORE = {'sim', 'hardware', 'vision', 'data', 'model', 'control'}
APP = {'nodes', 'commands', 'demo', 'cli', 'processes'}
ROS = ('rclpy', 'launch', 'launch_ros')
# Imports that break a rule today, each with where it is going; an entry that no longer
# occurs is simply unused (other work removes these; nothing else may join them).
PENDING = {}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix('').parts)
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def import_graph() -> tuple[dict, dict]:
    """Return {module: {package modules it imports}} and {module: {outside names}}."""
    files = {module_name(p): p for p in PKG.rglob('*.py')}
    inside, outside = {}, {}
    for mod, path in files.items():
        here = mod if path.name == '__init__.py' else mod.rsplit('.', 1)[0]
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ''
                if node.level:
                    up = here.split('.')[:len(here.split('.')) - node.level + 1]
                    base = '.'.join(up + ([base] if base else []))
                subs = {f'{base}.{a.name}' for a in node.names if f'{base}.{a.name}' in files}
                names |= subs
                if len(subs) < len(node.names):     # names defined by the package itself
                    names.add(base)
        inside[mod] = {n for n in names if n in files and n != mod}
        outside[mod] = {n for n in names if not n.startswith('softshape_ros')}
    return inside, outside


def layer(mod: str) -> str:
    """'softshape_ros.sim.rig' -> 'sim'; 'softshape_ros.config' -> 'config'."""
    parts = mod.split('.')
    return parts[1] if len(parts) > 1 else 'softshape_ros'


def cycles(graph: dict) -> list[list[str]]:
    """Return the strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_rule_checks_find_what_they_look_for():
    """The checks on a made-up graph: a cycle is found, a clean graph passes."""
    assert cycles({'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a'}}) == [['a', 'b', 'c']]
    assert cycles({'a': {'b'}, 'b': set()}) == []
    inside, outside = import_graph()
    assert 'softshape_ros.data.bag_tools' in inside['softshape_ros.data.bag_writer']
    assert 'rclpy' in {n.split('.')[0] for n in outside['softshape_ros.nodes.recorder']}


def test_no_import_cycle_between_modules():
    inside, _ = import_graph()
    found = cycles(inside)
    assert not found, 'import cycles (lazy imports included): ' + '; '.join(
        ' <-> '.join(c) for c in found)


def test_no_import_cycle_between_layers():
    inside, _ = import_graph()
    layers = defaultdict(set)
    for mod, deps in inside.items():
        layers[layer(mod)] |= {layer(d) for d in deps if layer(d) != layer(mod)
                               and (mod, d) not in PENDING}
    found = cycles(layers)
    assert not found, f'layers importing each other: {found}'


def test_each_layer_imports_only_what_it_may():
    inside, outside = import_graph()
    broken = []
    for mod, deps in sorted(inside.items()):
        me = layer(mod)
        for dep in sorted(deps):
            them = layer(dep)
            if (mod, dep) in PENDING or them == me:
                continue
            if me in FLOOR and them not in FLOOR:
                broken.append(f'{mod} -> {dep}: the floor imports no layer')
            if me in CORE | FLOOR and them in APP:
                broken.append(f'{mod} -> {dep}: core imports no node, command or demo')
            if {me, them} == {'model', 'sim'}:
                broken.append(f'{mod} -> {dep}: model/ and sim/ do not import each other')
            if them == 'hardware' and me in CORE:
                broken.append(f'{mod} -> {dep}: only the application layer drives hardware/')
        if me in CORE | FLOOR | {'softshape_ros'}:
            ros = sorted(n for n in outside[mod] if n.split('.')[0] in ROS)
            if ros:
                broken.append(f'{mod} imports {ros}: the core is plain Python')
    assert not broken, '\n'.join(broken)


def test_importing_the_core_loads_no_ros_client_library():
    """Import every core module for real: nothing pulls rclpy in, directly or through a library."""
    inside, _ = import_graph()
    core = sorted(m for m in inside if layer(m) in CORE | FLOOR)
    code = ('import importlib, json, sys\n'
            f'for m in {core!r}:\n'
            '    importlib.import_module(m)\n'
            'print(json.dumps(sorted(n for n in sys.modules if n.split(".")[0] in '
            f'{ROS!r} or n.startswith("softshape_ros.nodes"))))\n')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         timeout=300, cwd=PKG.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []
