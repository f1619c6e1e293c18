"""The declared numeric tolerance for notebook outputs (vpr_nb/output_tolerance.py, notebooks/conftest.py)."""
import pytest

from vpr_nb.output_tolerance import align_to_reference, cell_tolerance, tolerant_equal


def test_marker_is_read_and_checked():
    assert cell_tolerance("x = 1\n# NBVAL_TOLERANCE=0.02\nprint(x)") == (0.02, 0.0)
    assert cell_tolerance("# NBVAL_TOLERANCE=0.01 rel=0.05") == (0.01, 0.05)
    assert cell_tolerance("print(1)  # no marker") is None
    assert cell_tolerance("# NBVAL_TOLERANCE=0.02   trained numbers") == (0.02, 0.0)
    with pytest.raises(ValueError, match="cannot read"):
        cell_tolerance("# NBVAL_TOLERANCE=two")
    with pytest.raises(ValueError, match="rel"):
        cell_tolerance("# NBVAL_TOLERANCE=0.01 rel=2")


def test_decimals_within_tolerance_pass_and_everything_else_must_match():
    ref = "R@1 0.416, loss 1.347 after 16 steps (lr 0.001)"
    assert tolerant_equal(ref, "R@1 0.421, loss 1.351 after 16 steps (lr 0.001)", 0.02)
    assert not tolerant_equal(ref, "R@1 0.446, loss 1.351 after 16 steps (lr 0.001)", 0.02)   # beyond
    assert not tolerant_equal(ref, "R@1 0.421, loss 1.351 after 17 steps (lr 0.001)", 0.02)   # an integer
    assert not tolerant_equal(ref, "R@5 0.421, loss 1.351 after 16 steps (lr 0.001)", 0.02)   # a word
    assert not tolerant_equal(ref, "R@1 0.421, loss 1.351 after 16 steps", 0.02)              # a number fewer
    assert tolerant_equal("−0.050 ± 0.012", "−0.061 ± 0.010", 0.02)                          # unicode minus
    assert not tolerant_equal("gap 10.00", "gap 10.60", 0.02) and tolerant_equal("gap 10.00", "gap 10.40", 0.0, 0.05)


def test_align_returns_the_reference_only_when_within():
    assert align_to_reference("0.500", "0.510", 0.02) == "0.500"
    assert align_to_reference("0.500", "0.600", 0.02) == "0.600"


NOTEBOOK = '''{"cells": [
 {"cell_type": "code", "execution_count": 1, "id": "a", "metadata": {}, "source": "# NBVAL_TOLERANCE=0.02\\nprint('R@1 0.421')",
  "outputs": [{"name": "stdout", "output_type": "stream", "text": "R@1 %s\\n"}]},
 {"cell_type": "code", "execution_count": 2, "id": "b", "metadata": {}, "source": "print('R@1 0.421')",
  "outputs": [{"name": "stdout", "output_type": "stream", "text": "R@1 %s\\n"}]}],
 "metadata": {"kernelspec": {"display_name": "Python 3 (ipykernel)", "language": "python", "name": "python3"}},
 "nbformat": 4, "nbformat_minor": 5}'''


@pytest.mark.slow
def test_nbval_applies_the_marker_only_to_marked_cells(tmp_path):
    """Under nbval, the marked cell passes within tolerance and fails beyond it; the unmarked cell is exact."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path
    shutil.copy(Path(__file__).parents[1] / "notebooks" / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "near.ipynb").write_text(NOTEBOOK % ("0.416", "0.421"))
    (tmp_path / "far.ipynb").write_text(NOTEBOOK % ("0.456", "0.421"))
    (tmp_path / "unmarked.ipynb").write_text(NOTEBOOK % ("0.421", "0.416"))
    run = subprocess.run([sys.executable, "-m", "pytest", "--nbval", "--nbval-current-env", "-p", "no:cacheprovider",
                          "-q", "-rf", "--rootdir", str(tmp_path), str(tmp_path)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    out = run.stdout
    failed = sorted(line.split()[1] for line in out.splitlines() if line.startswith("FAILED"))
    assert failed == ["far.ipynb::Cell", "unmarked.ipynb::Cell"], out
    assert "far.ipynb::Cell 0" in out and "unmarked.ipynb::Cell 1" in out and "4 passed" in out, out
