"""Reading a point cloud by its file's extension: PLY (`_ply.py`), PCD (`_pcd.py`), and NumPy
`.npy` / `.npz` arrays (here).

Everything here runs on the host with NumPy and returns NumPy arrays (wrap them with
`jnp.asarray` to hand them to `lieax.icp`); there is no dependency beyond NumPy.
"""

import os

import numpy as np
import numpy.typing as npt

from ._common import PointCloudData
from ._pcd import read_pcd
from ._ply import read_ply


def read_point_cloud(
    path: str | os.PathLike[str], *, key: str | None = None, dtype: npt.DTypeLike = np.float64
) -> PointCloudData:
    """Read a `.ply`, `.pcd`, `.npy` or `.npz` file, choosing the format by the extension.

    **Arguments:**

    - `path`: the file.
    - `key`: for `.npz`, the array to read (default `points`, or the only array in the file).
      An `.npy`/`.npz` array of shape `(n, 3)` holds points; `(n, 6)` points then normals.
    - `dtype`: of `points`, `normals` and `colors`.

    **Raises:** `PointCloudFileError` (a `ValueError`) for a PLY or PCD file that cannot be read,
    naming the file and the line or byte (see `read_ply`, `read_pcd`); `ValueError` for an
    unknown extension or an array of the wrong shape.
    """
    extension = os.path.splitext(str(path))[1].lower()
    if extension == ".ply":
        return read_ply(path, dtype=dtype)
    if extension == ".pcd":
        return read_pcd(path, dtype=dtype)
    if extension in (".npy", ".npz"):
        return _read_numpy(path, key, dtype)
    raise ValueError(
        f"Unknown point cloud format {extension!r} for {path}: expected .ply, .pcd, .npy or .npz."
    )


# ---- NumPy --------------------------------------------------------------------------------------


def _read_numpy(path, key, dtype):
    if str(path).lower().endswith(".npy"):
        array = np.load(path, allow_pickle=False)
        where = str(path)
    else:
        with np.load(path, allow_pickle=False) as archive:
            names = list(archive.keys())
            if key is None:
                if "points" in names:
                    key = "points"
                elif len(names) == 1:
                    key = names[0]
                else:
                    raise ValueError(
                        f"{path} holds several arrays ({', '.join(names)}); pass key= to choose one."
                    )
            if key not in names:
                raise KeyError(f"{path} has no array {key!r} (it has {', '.join(names)}).")
            array = archive[key]
        where = f"{path}[{key!r}]"
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] not in (3, 6):
        raise ValueError(
            f"{where} must have shape (n, 3) (points) or (n, 6) (points, normals), got {array.shape}."
        )
    normals = array[:, 3:6].astype(dtype) if array.shape[1] == 6 else None
    fields = {
        name: array[:, i]
        for i, name in enumerate(("x", "y", "z", "nx", "ny", "nz")[: array.shape[1]])
    }
    return PointCloudData(array[:, :3].astype(dtype), normals, None, fields)
