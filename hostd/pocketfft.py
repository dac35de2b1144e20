"""scipy.fft's transforms (pocketfft), without importing scipy.fft.

`import scipy.fft` costs a command line about 0.2 s of CPU (it imports scipy.special and the
array-API layer), a third of `hostd encode --target-iobj` (DEVELOPMENT.md, "Guards"), for
the one C++ routine the codec and SPQI use. This module loads that routine, scipy's compiled
`scipy.fft._pocketfft.pypocketfft`, by its file (about 1 ms) and calls it exactly as
scipy.fft.dct, fft, ifft and irfft do with their default arguments (the same code, so the same bits:
tests/test_lean.py compares them). It checks the routine against known values when it loads;
anything unexpected (another scipy's layout or signature) falls back to scipy.fft itself.
"""

from __future__ import annotations

import math

import numpy as np

_NORM = {None: 0, "ortho": 1}  # pocketfft's inorm: 0 none, 1 1/sqrt(n), 2 1/n


def _load():
    """pypocketfft, loaded from scipy's installation without scipy's package inits; None if
    unavailable or not behaving as expected."""
    import importlib.machinery
    import importlib.util
    import sys
    from pathlib import Path

    name = "scipy.fft._pocketfft.pypocketfft"
    try:
        mod = sys.modules.get(name)
        if mod is None:
            spec = importlib.util.find_spec("scipy")  # (finds the package, runs none of it)
            if spec is None or not spec.submodule_search_locations:
                return None
            d = Path(next(iter(spec.submodule_search_locations)), "fft", "_pocketfft")
            so = next(iter(sorted(d.glob("pypocketfft*" + importlib.machinery.EXTENSION_SUFFIXES[0]))), None)
            if so is None:
                return None
            loader = importlib.machinery.ExtensionFileLoader(name, str(so))
            spec = importlib.util.spec_from_file_location(name, so, loader=loader)
            mod = importlib.util.module_from_spec(spec)
            loader.exec_module(mod)
            sys.modules[name] = mod  # scipy.fft, if imported later, uses this one (no second init)
        # known values: DCT-II of (1, 2) = (6, -sqrt 2); DCT-III; a complex FFT and its inverse
        y = mod.dct(np.array([1.0, 2.0]), 2, (-1,), 0, None, 1, None)
        z = mod.c2c(np.array([1.0 + 0j, 1j]), (-1,), True, 0, None, 1)
        w = mod.c2c(z, (-1,), False, 2, None, 1)
        if not (abs(y[0] - 6.0) < 1e-12 and abs(y[1] + math.sqrt(2.0)) < 1e-12
                and abs(z[0] - (1 + 1j)) < 1e-12 and abs(z[1] - (1 - 1j)) < 1e-12
                and abs(w[1] - 1j) < 1e-12 and mod.good_size(1021, False) >= 1021):
            return None
        return mod
    except Exception:  # another layout, signature or build of scipy: scipy.fft itself
        return None


_P = _load()
IMPLEMENTATION = "pypocketfft" if _P is not None else "scipy.fft"


def dct(x, type: int = 2, norm: str | None = None, axis: int = -1, overwrite_x: bool = False) -> np.ndarray:
    """scipy.fft.dct(x, type, norm=norm, axis=axis, overwrite_x=overwrite_x) for float64 x."""
    if _P is None or norm not in _NORM or x.dtype != np.float64:
        import scipy.fft

        return scipy.fft.dct(x, type=type, norm=norm, axis=axis, overwrite_x=overwrite_x)
    if x.shape[axis] < 1:
        raise ValueError(f"invalid number of data points ({x.shape[axis]}) specified")
    return _P.dct(x, type, (axis,), _NORM[norm], x if overwrite_x else None, 1, None)


def _c2c(x, n: int | None, forward: bool) -> np.ndarray:
    x = np.asarray(x)
    if _P is None or x.dtype != np.complex128:
        import scipy.fft

        return (scipy.fft.fft if forward else scipy.fft.ifft)(x, n)
    out = None
    if n is not None and n != x.shape[-1]:  # scipy.fft's _fix_shape_1d: cut, or zero-padded copy
        if n < 1:
            raise ValueError(f"invalid number of data points ({n}) specified")
        if x.shape[-1] >= n:
            x = x[..., :n]
        else:
            z = np.zeros((*x.shape[:-1], n), x.dtype)
            z[..., : x.shape[-1]] = x
            x = out = z
    return _P.c2c(x, (-1,), forward, 0 if forward else 2, out, 1)


def fft(x, n: int | None = None) -> np.ndarray:
    """scipy.fft.fft(x, n) along the last axis, complex128 x."""
    return _c2c(x, n, True)


def ifft(x, n: int | None = None) -> np.ndarray:
    """scipy.fft.ifft(x, n) along the last axis, complex128 x."""
    return _c2c(x, n, False)


def irfft(x, n: int) -> np.ndarray:
    """scipy.fft.irfft(x, n) along the last axis (x complex128, or real: taken as complex)."""
    x = np.asarray(x)
    if _P is None or x.dtype not in (np.complex128, np.float64):
        import scipy.fft

        return scipy.fft.irfft(x, n)
    if x.dtype == np.float64:
        x = x + 0.0j
    m = n // 2 + 1
    if n < 1:
        raise ValueError(f"invalid number of data points ({n}) specified")
    if x.shape[-1] >= m:
        x = x[..., :m]
    else:
        z = np.zeros((*x.shape[:-1], m), x.dtype)
        z[..., : x.shape[-1]] = x
        x = z
    return _P.c2r(x, (-1,), n, False, 2, None, 1)


def next_fast_len(target: int) -> int:
    """scipy.fft.next_fast_len(target) (complex transforms)."""
    if _P is None:
        import scipy.fft

        return scipy.fft.next_fast_len(target)
    return _P.good_size(target, False)
