"""The one exception type for bad input, and the words its messages use."""

import numpy as np


class DataError(ValueError):
    """Bad input: the message is one line that names the problem."""


def dtype_word(dtype) -> str:
    """A reader's word for a non-real dtype in an error message (`complex`, `boolean`...).

    **Arguments:**

    - `dtype`: a NumPy dtype, or anything `np.dtype` accepts.

    **Returns:** the word (`"complex"`, `"boolean"`, `"string"`, `"bytes"`, `"object"`, `"datetime"`), or
    the dtype's name for any other kind.
    """
    dtype = np.dtype(dtype)
    words = {"c": "complex", "b": "boolean", "U": "string", "S": "bytes", "O": "object", "M": "datetime"}
    return words.get(dtype.kind, str(dtype))
