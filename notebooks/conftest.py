"""nbval on the pinned CPU kernels, with a declared numeric tolerance for cells marked ``# NBVAL_TOLERANCE=...``.

The kernels nbval starts inherit :data:`vpr_nb.kernels.PINNED` (set here, before any kernel starts), the
environment the stored outputs were recorded in (``make notebook``), so a trained number is the same bits on
any x86-64 machine. A marked cell's re-run passes when its text equals the stored one with every decimal
number within the tolerance (``vpr_nb/output_tolerance.py``); every other cell is compared exactly, as
nbval does."""
from __future__ import annotations

import copy

from vpr_nb.kernels import pin_this_process

pin_this_process()

try:
    from nbval import plugin as _nbval
except ImportError:          # nbval not installed: nothing to adjust
    _nbval = None

from vpr_nb.output_tolerance import align_to_reference, cell_tolerance

if _nbval is not None and not getattr(_nbval.IPyNbCell, "_vpr_tolerance", False):
    _compare = _nbval.IPyNbCell.compare_outputs

    def compare_outputs(self, test, ref, skip_compare=None):
        tol = cell_tolerance(self.cell.source)
        if tol is not None:
            test = [_aligned(t, r, tol) for t, r in zip(test, ref)] + list(test[len(ref):])
        return _compare(self, test, ref, skip_compare)

    def _aligned(test_out, ref_out, tol):
        """A copy of one test output whose text fields take the stored text where within tolerance."""
        out = copy.copy(test_out)        # a NotebookNode stays one (nbval reads out.output_type)
        if out.get("output_type") != ref_out.get("output_type"):
            return test_out
        if "text" in out and isinstance(ref_out.get("text"), str) and isinstance(out["text"], str):
            out["text"] = align_to_reference(ref_out["text"], out["text"], *tol)
        if isinstance(out.get("data"), dict) and isinstance(ref_out.get("data"), dict):
            data = copy.copy(out["data"])
            for key in ("text/plain", "text/html", "text/markdown"):
                if isinstance(data.get(key), str) and isinstance(ref_out["data"].get(key), str):
                    data[key] = align_to_reference(ref_out["data"][key], data[key], *tol)
            out["data"] = data
        return out

    _nbval.IPyNbCell.compare_outputs = compare_outputs
    _nbval.IPyNbCell._vpr_tolerance = True
