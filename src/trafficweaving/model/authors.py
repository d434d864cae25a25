"""Import of the authors' trained TensorFlow weights (``weights.npz``, keyed by TensorFlow name).

Every tensor is mapped by name onto :class:`CVAE` with its shape checked. TensorFlow dense kernels
are ``[inputs, outputs]`` (transposed into ``nn.Linear``); LSTM kernels ``[inputs + units, 4·units]``
are split into their input and recurrent rows. The published model is the paper's CVAE without the
recognition network q(z|x,y), which prediction does not need.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from .checkpoint import check_tensors
from .cvae import CVAE, CVAEConfig

LSTM = "multi_rnn_cell/cell_0/layer_norm_basic_lstm_cell"
ROBOT_FUTURE = "car_future_rnn/car1"


def _lstm(prefix: str, module: str) -> list[tuple[str, str, str]]:
    return [(f"{prefix}/{LSTM}/kernel", f"{module}", "lstm_kernel"), (f"{prefix}/{LSTM}/bias", f"{module}.bias", "copy")]


def _dense(name: str, module: str) -> list[tuple[str, str, str]]:
    return [(f"{name}/kernel", f"{module}.weight", "transpose"), (f"{name}/bias", f"{module}.bias", "copy")]


def _projection(prefix: str, module: str) -> list[tuple[str, str, str]]:
    return [*_dense(f"{prefix}/initial_state_projection/cell_0/initial_c", f"{module}.initial_c"),
            *_dense(f"{prefix}/initial_state_projection/cell_0/initial_h", f"{module}.initial_h")]


WEIGHT_MAP = [  # (TensorFlow name, parameter of CVAE, conversion)
    *_lstm("car_history_rnn/rnn", "history_encoder"),
    *_lstm(f"{ROBOT_FUTURE}/bidirectional_rnn/fw", "robot_future_encoder.cell"),
    *_projection(ROBOT_FUTURE, "robot_future_encoder.initial_state"),
    *_dense("encoder/p_z_x/dense0", "p_z_hidden"),
    *_dense("encoder/p_z_x/projection", "p_z_out"),
    *_projection("decoder/p_y_xz", "decoder_initial_state"),
    *_lstm("decoder/p_y_xz/rnn", "decoder"),
    *_dense("decoder/p_y_xz/rnn/log_pi_projection", "gmm.log_pi"),
    *_dense("decoder/p_y_xz/rnn/mu_projection", "gmm.mu"),
    *_dense("decoder/p_y_xz/rnn/log_sigma_projection", "gmm.log_sigma"),
    *_dense("decoder/p_y_xz/rnn/corr_projection", "gmm.corr"),
    ("features_standardization/train_mean", "feature_mean", "copy"),
    ("features_standardization/train_std", "feature_std", "copy"),
    ("label_standardization/train_mean", "label_mean", "copy"),
    ("label_standardization/train_std", "label_std", "copy"),
]
UNUSED = {"global_step", "features_standardization/train_extras_mean", "features_standardization/train_extras_std"}


def _expected_shape(model: CVAE, target: str, conversion: str) -> tuple[int, ...]:
    """The shape the TensorFlow array of ``target`` must have."""
    if conversion == "lstm_kernel":
        cell = model.get_submodule(target)
        return (cell.input_size + cell.units, 4 * cell.units)
    shape = tuple((dict(model.named_parameters()) | dict(model.named_buffers()))[target].shape)
    return shape[::-1] if conversion == "transpose" else shape


def _read_npz(path: Path, expected: str) -> dict[str, np.ndarray]:
    """Every array of the .npz file ``path`` (no pickles); :class:`InputError` naming it otherwise."""
    if path.is_dir():
        raise InputError(f"{path}: is a folder (expected {expected})")
    if not path.is_file():
        raise InputError(f"{path}: no such file (expected {expected})")
    try:
        with np.load(path, allow_pickle=False) as npz:
            if not isinstance(npz, np.lib.npyio.NpzFile):
                raise TypeError("a single array")
            return {k: np.asarray(npz[k]) for k in npz.files}
    except Exception as exc:  # zipfile/ValueError/OSError/...: any unreadable file is a user error here
        raise InputError(f"{path}: not a readable .npz file ({type(exc).__name__}; expected {expected})") from None


def load_authors_model(path: str | Path) -> CVAE:
    """The authors' published CVAE from their ``weights.npz``, in evaluation mode.

    Raises :class:`InputError` naming the file on a missing, unreadable or non-.npz file, and naming
    the file and array ("tensor NAME") on a missing, misshapen, non-float or non-finite array, a
    non-positive standard deviation (the value checks of a checkpoint) or an unexpected extra array.
    """
    path = Path(path)
    expected = "the authors' weights.npz, arrays keyed by TensorFlow variable name (docs/model.md)"
    weights = _read_npz(path, expected)
    model = CVAE(CVAEConfig(has_q=False))
    state = {}
    for tf_name, target, conversion in WEIGHT_MAP:
        if tf_name not in weights:
            raise InputError(f"{path}: missing tensor {tf_name} (expected {expected})")
        array, shape = weights[tf_name], _expected_shape(model, target, conversion)
        if not np.issubdtype(array.dtype, np.floating):
            raise InputError(f"{path}: tensor {tf_name} has dtype {array.dtype} (expected floating point weights)")
        if array.shape != shape:
            raise InputError(f"{path}: tensor {tf_name} has shape {list(array.shape)} (expected {list(shape)})")
        with np.errstate(over="ignore"):  # a float64 value beyond float32 becomes inf, refused below
            value = torch.from_numpy(array.astype(np.float32))
        if conversion == "lstm_kernel":
            split = model.get_submodule(target).input_size
            state |= {f"{target}.weight_input": value[:split], f"{target}.weight_hidden": value[split:]}
        else:
            state[target] = value.T if conversion == "transpose" else value
    extra = set(weights) - {n for n, _, _ in WEIGHT_MAP} - UNUSED
    if extra:
        raise InputError(f"{path}: unexpected tensor {sorted(extra)[0]} (expected {expected})")
    names = {target: tf_name for tf_name, target, _ in WEIGHT_MAP}
    expected_state = model.state_dict()
    # NaN/inf (also float64 values overflowing float32) and standard deviations <= 0, named by array
    check_tensors(state, expected_state, path, lambda name: f"tensor {names.get(name) or names[name.rsplit('.', 1)[0]]}")
    model.load_state_dict({**expected_state, **state})
    return model.eval()
