"""Writes the numpy pickles the pickle reader's unit tests read (run once; the .pkl files are
committed). Run with numpy 2.x: `python3 make.py`, and with numpy 1.26 on the path for the
`np1_*` files: `PYTHONPATH=<numpy 1.26> python3 make.py`."""
import pickle

import numpy as np


def sample():
    a = np.arange(6, dtype=np.float32).reshape(2, 3) / 4
    return {
        "f4": a,
        "f4_again": a + 1,  # a second float32 array: numpy refers back to the first's dtype
        "f8_fortran": np.asfortranarray(np.arange(6, dtype=np.float64).reshape(2, 3)),
        "big_endian": np.array([1.5, -2.25], dtype=">f4"),
        "b1": np.array([[True, False, True], [False, False, True]]),
        "i8": np.array([-3, 0, 7], dtype=np.int64),
        "u2": np.array([1, 65535], dtype=np.uint16),
        "scalar": np.float64(2.5),
        "empty": np.zeros((0, 3)),
        "plain": [1, 2.5, "text", (None, True, False), {"k": -70000}],
    }


major = int(np.__version__.split(".")[0])
protocols = (2, 4, 5) if major >= 2 else (2, 4)
for proto in protocols:
    with open(f"np{major}_p{proto}.pkl", "wb") as f:
        pickle.dump(sample(), f, protocol=proto)
