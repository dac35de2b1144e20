"""MATLAB .mat profiles (v4 to v7, scipy.io.loadmat; imported only when a .mat file is read).

A .mat file is a container: the array taken is the one numeric variable it holds, or the one
`--var NAME` (LoadOptions.member) names; `--var X,Y` pairs two vectors as x and height. A
vector (N,), (N, 1) or (1, N) is heights; (N, 2) or (2, N) is x, height. v7.3 files are HDF5,
which scipy does not read: the message says how to save the file so that it can.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hostd.errors import ProfileError, ProfileNotFound
from hostd.texture.formats import Columns

V73_HINT = ("is a MATLAB v7.3 (HDF5) file, which hostd cannot read: save it as v7 in MATLAB "
            "(save('profile.mat', 'NAME', '-v7')) or write the array as CSV (writematrix)")


def _numeric(v) -> bool:
    return (isinstance(v, np.ndarray) and v.size > 0 and v.dtype.kind in "biuf"
            and v.ndim <= 2)


def _load(p: Path) -> dict[str, np.ndarray]:
    import scipy.io
    from scipy.io.matlab import matfile_version

    if not p.exists():
        raise ProfileNotFound(f"no such profile file: {p}")
    try:
        with p.open("rb") as fh:
            major, _minor = matfile_version(fh)
        if major == 2:
            raise ProfileError(f"{p} {V73_HINT}")
        return scipy.io.loadmat(p, squeeze_me=False, struct_as_record=True)
    except NotImplementedError:  # scipy's own word for v7.3
        raise ProfileError(f"{p} {V73_HINT}") from None
    except ProfileError:
        raise
    except Exception as exc:  # scipy raises ValueError, TypeError, OSError ... on a broken file
        raise ProfileError(f"cannot read {p} as a MATLAB .mat file: {exc}") from None


def _as_columns(p: Path, name: str, v: np.ndarray) -> np.ndarray:
    if v.dtype.kind == "c":
        raise ProfileError(f"{p}: variable {name!r} is complex: heights must be real")
    a = np.asarray(v, dtype=np.float64)
    if a.ndim <= 1 or 1 in a.shape:
        return a.reshape(-1, 1)
    if a.shape[1] == 2:
        return a
    if a.shape[0] == 2:
        return a.T.copy()
    raise ProfileError(f"{p}: variable {name!r} has shape {a.shape}; a profile is a vector of heights "
                       "or two columns x, height (--var X,Y pairs two vectors)")


def read_mat(p: Path, opts) -> Columns:
    """The .mat reader of the format registry (hostd.texture.formats)."""
    variables = {k: v for k, v in _load(p).items() if not k.startswith("__")}
    numeric = {k: v for k, v in variables.items() if _numeric(v)}
    listing = ", ".join(f"{k} {'x'.join(map(str, v.shape))}" for k, v in numeric.items()) or "none"
    member = opts.member
    if member is None:
        if len(numeric) != 1:
            what = "no numeric array" if not numeric else f"several arrays ({listing})"
            raise ProfileError(f"{p} holds {what}: choose one with --var NAME (or --var X,Y for "
                               "an x and a height vector)")
        ((name, v),) = numeric.items()
        return Columns(_as_columns(p, name, v), note=f"read its one numeric variable, {name!r}")
    names = [s.strip() for s in member.split(",")]
    for n in names:
        if n not in variables:
            raise ProfileError(f"{p} has no variable {n!r} (its numeric arrays: {listing})")
        if not _numeric(variables[n]):
            raise ProfileError(f"{p}: variable {n!r} is not a numeric array (its numeric arrays: {listing})")
    if len(names) == 1:
        return Columns(_as_columns(p, names[0], variables[names[0]]))  # what --var asked: nothing to note
    if len(names) != 2:
        raise ProfileError(f"--var {member!r}: give NAME, or X,Y (two vectors)")
    x, y = (_as_columns(p, n, variables[n]) for n in names)
    if x.shape[1] != 1 or y.shape[1] != 1 or x.shape[0] != y.shape[0]:
        raise ProfileError(f"--var {member}: {names[0]} and {names[1]} must be vectors of one length "
                           f"({listing})")
    return Columns(np.column_stack([x[:, 0], y[:, 0]]))
