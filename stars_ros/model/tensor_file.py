"""Read a ``torch.save`` file into numpy arrays and plain values, without importing torch.

A robot's ranker reads its checkpoint at start, where importing torch alone costs more
than a second (docs/performance.md), and serving a graph model needs no torch at all. The
file is a zip: ``<root>/data.pkl``, the pickled structure, and one file per tensor storage,
``<root>/data/<key>``. The pickle is read with an unpickler that knows four kinds of name
(the tensor rebuild, the storage types, ``OrderedDict``) and refuses every other, as
``torch.load(weights_only=True)`` does: no pickled code ever runs. Files are written with
``torch.save`` (``model.checkpoint``), and ``test/model/test_checkpoint.py`` checks this
reader against ``torch.load`` on them.
"""
from __future__ import annotations

import collections
import pickle
import zipfile

import numpy as np

STORAGE_DTYPES = {'FloatStorage': np.float32, 'DoubleStorage': np.float64, 'HalfStorage': np.float16,
                  'LongStorage': np.int64, 'IntStorage': np.int32, 'ShortStorage': np.int16,
                  'CharStorage': np.int8, 'ByteStorage': np.uint8, 'BoolStorage': np.bool_}


class UnsupportedGlobal(pickle.UnpicklingError):
    """The file names a Python object that is neither a tensor nor a plain value."""


class _StorageType:
    def __init__(self, name: str):
        self.dtype = np.dtype(STORAGE_DTYPES[name])


def _rebuild_tensor(storage: np.ndarray, offset: int, size: tuple, stride: tuple, *_) -> np.ndarray:
    """``torch._utils._rebuild_tensor_v2``'s array: ``size`` elements of ``storage`` from
    ``offset`` with ``stride`` (in elements), copied into a contiguous array of its own."""
    view = np.lib.stride_tricks.as_strided(storage[offset:], shape=tuple(size),
                                           strides=tuple(s * storage.itemsize for s in stride), writeable=False)
    return np.array(view, copy=True, order='C')


class _Unpickler(pickle.Unpickler):
    def __init__(self, archive: zipfile.ZipFile, root: str, handle):
        super().__init__(handle)
        self._archive, self._root, self._storages = archive, root, {}

    def find_class(self, module: str, name: str):
        if (module, name) == ('collections', 'OrderedDict'):
            return collections.OrderedDict
        if (module, name) == ('torch._utils', '_rebuild_tensor_v2'):
            return _rebuild_tensor
        if module == 'torch' and name in STORAGE_DTYPES:
            return _StorageType(name)
        raise UnsupportedGlobal(f'Unsupported global: GLOBAL {module}.{name}')

    def persistent_load(self, pid):
        kind, storage_type, key, _location, count = pid
        if kind != 'storage' or not isinstance(storage_type, _StorageType):
            raise pickle.UnpicklingError(f'unknown persistent id {kind!r}')
        if key not in self._storages:
            data = self._archive.read(f'{self._root}/data/{key}')
            if len(data) != count * storage_type.dtype.itemsize:
                raise pickle.UnpicklingError(f'storage {key} holds {len(data)} bytes, not {count} elements')
            self._storages[key] = np.frombuffer(data, dtype=storage_type.dtype)
        return self._storages[key]


def read_tensor_file(path) -> object:
    """The content ``torch.save`` wrote to ``path``, tensors as numpy arrays. Raises
    OSError (FileNotFoundError for a missing file), zipfile.BadZipFile (not a zip),
    UnsupportedGlobal (a name besides tensors and plain values), pickle.UnpicklingError,
    EOFError, KeyError or ValueError (truncated or corrupted)."""
    with zipfile.ZipFile(path) as archive:
        pickles = [name for name in archive.namelist() if name.endswith('/data.pkl') and name.count('/') == 1]
        if len(pickles) != 1:
            raise pickle.UnpicklingError('no data.pkl at the top of the archive')
        root = pickles[0].split('/')[0]
        names = set(archive.namelist())
        if f'{root}/byteorder' in names and archive.read(f'{root}/byteorder') != b'little':
            raise ValueError('written on a big-endian machine')
        with archive.open(pickles[0]) as handle:
            return _Unpickler(archive, root, handle).load()
