"""The renderer's tail on the real-time path (equalizer -> output stage -> DAC codes) for a
small batch, by the compiled hostd/render/_fastrender.c when it is built, else by the Python
stages themselves (Equalizer.__call__, OutputStage.process and to_codes: the reference, the
same codes and the same filter/envelope state sample for sample).

Only batches the reference runs in scalar Python (<= equalizer.SMALL_BATCH samples) and int16
codes (dac_bits <= 16) take the compiled path; larger ones are cheap per sample in numpy anyway.
HOSTD_PURE_PYTHON=1 (any value but 0) selects the reference, as for the range coder.
"""

from __future__ import annotations

import numpy as np

from hostd.compiled import load as load_compiled
from hostd.render.equalizer import SMALL_BATCH, Equalizer
from hostd.render.output import OutputStage

C_REVISION = 3  # _fastrender.c's REVISION this module is written for
_NO_SECTIONS = np.zeros((0, 6))


_C = load_compiled("hostd.render._fastrender", C_REVISION)
IMPLEMENTATION = "c" if _C is not None else "python"


def tail_py(eq: Equalizer, out: OutputStage, h_um: np.ndarray) -> np.ndarray:
    """The reference: heights (µm, before the equalizer) -> DAC codes, updating both stages."""
    return out.to_codes(out.process(eq(h_um)))


def tail(eq: Equalizer, out: OutputStage, h_um: np.ndarray) -> np.ndarray:
    """tail_py's codes and state changes, compiled when that applies."""
    x = np.asarray(h_um, dtype=np.float64)
    if _C is None or x.size > SMALL_BATCH or out._code_dtype is not np.int16 or x.ndim != 1:
        return tail_py(eq, out, x)
    sos = eq.sos if eq.sos is not None else _NO_SECTIONS
    zi = eq.zi if eq.zi is not None else _NO_SECTIONS[:, :2]
    if not (zi.flags.c_contiguous and zi.flags.writeable and zi.dtype == np.float64
            and sos.flags.c_contiguous and sos.dtype == np.float64):
        return tail_py(eq, out, x)
    codes = np.empty(x.size, dtype=np.int16)
    _C.tail(sos, zi, np.ascontiguousarray(x), codes, out)  # out: read and updated as its record
    return codes
