"""Style checks as `ros2 pkg create` generates them (ament_flake8, ament_pep257)."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PATHS = [str(ROOT / p) for p in ('softshape_ros', 'test', 'benchmarks', 'launch', 'setup.py')
         if (ROOT / p).exists()]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    from ament_flake8.main import main_with_errors
    rc, errors = main_with_errors(argv=['--linelength', '99'] + PATHS)
    assert rc == 0, 'Found %d code style errors / warnings:\n' % len(errors) + '\n'.join(errors)


@pytest.mark.pep257
@pytest.mark.linter
def test_pep257():
    from ament_pep257.main import main
    rc = main(argv=PATHS)
    assert rc == 0, 'Found code style errors / warnings'
