"""The suite runs ruff over the whole workspace and mypy over the cores (pyproject.toml)."""

import pathlib
import shutil
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_ruff_clean():
    ruff = shutil.which('ruff') or str(pathlib.Path(sys.executable).with_name('ruff'))
    result = subprocess.run([ruff, 'check', str(ROOT)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_mypy_clean_over_the_cores():
    """The cores type-check (files and exceptions in pyproject.toml's [tool.mypy])."""
    result = subprocess.run([sys.executable, '-m', 'mypy'], cwd=ROOT, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def test_no_core_module_imports_rclpy():
    """Pure cores stay pure: only node adapters (``node.py``, ``*_node.py``) and tools may
    import rclpy."""
    allowed = ('node.py', 'ros_node.py')
    offenders = []
    for path in (ROOT / 'src').rglob('*.py'):
        if (path.name in allowed or path.name.endswith('_node.py')   # e.g. ship_node.py
                or 'deckland/deckland' in path.as_posix()):
            continue
        text = path.read_text()
        if 'import rclpy' in text or 'from rclpy' in text:
            offenders.append(str(path.relative_to(ROOT)))
    assert not offenders, f'core modules import rclpy: {offenders}'
