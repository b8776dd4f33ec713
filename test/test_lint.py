"""
Style checks as `ros2 pkg create` generates them (ament_flake8, ament_pep257).

Each runs in a fresh interpreter: flake8 checks files in forked worker processes, and a fork
of this test process, where earlier ROS tests left DDS and executor threads running, can
deadlock in the child (Python 3.12 warns about exactly that).
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = [str(ROOT / p) for p in ('softshape_ros', 'test', 'benchmarks', 'launch', 'setup.py')
         if (ROOT / p).exists()]

FLAKE8 = '''
import json, sys
from ament_flake8.main import main_with_errors
rc, errors = main_with_errors(argv=['--linelength', '99'] + sys.argv[1:])
print('\\n@@errors@@' + json.dumps(errors))
'''
PEP257 = '''
import sys
from ament_pep257.main import main
sys.exit(main(argv=sys.argv[1:]))
'''


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-c', code, *PATHS], cwd=ROOT, capture_output=True,
                          text=True, timeout=240)


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    proc = _run(FLAKE8)
    assert '@@errors@@' in proc.stdout, proc.stdout + proc.stderr
    errors = json.loads(proc.stdout.rsplit('@@errors@@', 1)[1])
    assert not errors, 'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)


@pytest.mark.pep257
@pytest.mark.linter
def test_pep257():
    proc = _run(PEP257)
    assert proc.returncode == 0, 'Found code style errors / warnings:\n' + proc.stdout[-4000:]
