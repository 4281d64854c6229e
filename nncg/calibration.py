"""Calibration inputs for nncg.quantize, read and checked before onnxruntime sees them.

Accepted: an .npz file whose keys are the model's input names, each array holding the samples along a
leading axis (shape (N, *input shape), e.g. (N, 1, 3, 60, 80) for an input [1, 3, 60, 80]); a folder of
.npy files, one sample each (shape = the input's), taken in file-name order, for a model with one input
(a model with several inputs takes an .npz); or the same in memory: a dict of input name to array, or one
array for a one-input model."""

from __future__ import annotations

import os
import zipfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import onnx

from .errors import NncgError
from .frontend.shapes import one_line, static_shape
from .safe_text import shown

PATH_LIMIT = 200  # characters of a path shown in a message


def calibration_samples(calibration: object, inputs: list[onnx.ValueInfoProto]) -> list[dict[str, np.ndarray]]:
    """One {input name: array} feed per sample, each checked against the model's `inputs` (static
    shapes). Raises NncgError for anything that does not fit."""
    names = [value.name for value in inputs]
    arrays = _arrays(calibration, names)
    _check_names(arrays, names)
    for value in inputs:
        _check_array(value, arrays[value.name])
    counts = {len(array) for array in arrays.values()}
    if len(counts) > 1:
        sizes = ", ".join(f"{shown(name)}: {len(arrays[name])}" for name in names)
        raise NncgError(f"the calibration inputs have different numbers of samples ({sizes}); give each input as many")
    return [{name: arrays[name][k] for name in names} for k in range(counts.pop())]


def _arrays(calibration: object, names: list[str]) -> dict[str, np.ndarray]:
    if isinstance(calibration, np.ndarray):
        if len(names) != 1:
            raise NncgError(
                f"one calibration array for a model with {len(names)} inputs ({', '.join(map(shown, names))}); "
                "give a dict of input name to array"
            )
        return {names[0]: calibration}
    if isinstance(calibration, Mapping):
        return {key: _in_memory(key, array) for key, array in calibration.items()}
    if isinstance(calibration, (str, os.PathLike)):
        path = Path(calibration)
        return _folder(path, names) if path.is_dir() else _npz(path)
    raise NncgError(
        "calibration must be an .npz path, a folder of .npy files, a dict of input name to numpy array, or "
        f"one numpy array; got {type(calibration).__name__}"
    )


def _in_memory(key: object, array: object) -> np.ndarray:
    if not isinstance(key, str) or not isinstance(array, np.ndarray):
        raise NncgError(
            f"calibration must map input names (str) to numpy arrays; got {type(key).__name__} -> "
            f"{type(array).__name__}"
        )
    return array


def _npz(path: Path) -> dict[str, np.ndarray]:
    where = shown(path, PATH_LIMIT)
    if not path.exists():
        raise NncgError(f"calibration file {where} does not exist; check the path")
    if path.suffix.lower() != ".npz":
        raise NncgError(
            f"calibration file {where} is not an .npz; give an .npz (numpy.savez) or a folder of .npy files"
        )
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise NncgError(f"cannot read calibration file {where}: {one_line(exc)} (write it with numpy.savez)") from None


def _folder(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    where = shown(path, PATH_LIMIT)
    if len(names) != 1:
        raise NncgError(
            f"calibration folder {where} for a model with {len(names)} inputs ({', '.join(map(shown, names))}): "
            "a folder of .npy files is for one-input models; give an .npz keyed by input name"
        )
    try:
        files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".npy")
    except OSError as exc:
        raise NncgError(f"cannot list calibration folder {where}: {one_line(exc)} (check its permissions)") from None
    if not files:
        raise NncgError(f"calibration folder {where} has no .npy files; put one sample per .npy file there")
    samples = [_npy(file) for file in files]
    shapes = {(sample.shape, sample.dtype) for sample in samples}
    if len(shapes) > 1:
        raise NncgError(f"the .npy files in {where} differ in shape or dtype; give every sample the input's shape")
    return {names[0]: np.stack(samples)}


def _npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise NncgError(
            f"cannot read calibration file {shown(path, PATH_LIMIT)}: {one_line(exc)} (write it with numpy.save)"
        ) from None


def _check_names(arrays: Mapping[str, np.ndarray], names: list[str]) -> None:
    missing = [name for name in names if name not in arrays]
    extra = [key for key in arrays if key not in names]
    if missing or extra:
        what = "lacks " + ", ".join(map(shown, missing)) if missing else "has " + ", ".join(map(shown, extra))
        raise NncgError(
            f"the calibration data {what}; it needs one array for each model input: {', '.join(map(shown, names))}"
        )


def _check_array(value: onnx.ValueInfoProto, array: np.ndarray) -> None:
    name = shown(value.name)
    dtype = onnx.helper.tensor_dtype_to_np_dtype(value.type.tensor_type.elem_type)
    shape = static_shape(value)
    if array.dtype != dtype:
        raise NncgError(
            f"calibration input {name} is {array.dtype}, the model takes {dtype}: convert it "
            f"(array.astype(numpy.{dtype}))"
        )
    if array.shape[1:] != shape:
        raise NncgError(
            f"calibration input {name} has shape {tuple(array.shape)}; the model takes {shape}, so it needs "
            f"(samples, {', '.join(map(str, shape))}): one input per sample along the first axis"
        )
    if len(array) == 0:
        raise NncgError(f"calibration input {name} has no samples; give at least one (a few hundred calibrate well)")
    if not np.isfinite(array).all():
        raise NncgError(f"calibration input {name} holds NaN or infinity; give finite values")
