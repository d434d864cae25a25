"""Checkpoint integrity: the tensor SHA-256, dtype/value/config/field checks on load, the authors'
.npz import's checks, and ``--device`` validation. Every refusal is one InputError line naming the
file or argument."""

from __future__ import annotations

import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from trafficweaving.errors import InputError
from trafficweaving.model.authors import load_authors_model
from trafficweaving.model.checkpoint import (HASH_FIELD, READABLE_VERSIONS, VERSION, export_checkpoint, load_checkpoint,
                                             read_checkpoint, save_checkpoint, tensor_digest, write_payload)
from trafficweaving.model.device import choose_device
from trafficweaving.model.registry import load_model, shipped_model_path
from trafficweaving.model.cvae import CVAE, CVAEConfig


def fails(path, pattern: str, name: str | None = None, loader=load_checkpoint) -> str:
    """Loading ``path`` raises a one-line InputError matching ``pattern`` and naming the file."""
    with pytest.raises(InputError, match=pattern) as info:
        loader(path)
    message = str(info.value)
    assert "\n" not in message and (name or Path(path).name) in message, message
    return message


@pytest.fixture
def model() -> CVAE:
    torch.manual_seed(0)
    return CVAE(CVAEConfig.variant("cvae-hold"))


@pytest.fixture
def saved(model, tmp_path) -> Path:
    """A valid checkpoint with training fields (optimizer, RNG, history) beside the model."""
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    for p in model.parameters():
        p.grad = torch.full_like(p, 0.01)
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, step=7, history=[(5, -1.5)], data_fingerprint="ab" * 32, train_config={"steps": 7},
                    optimizer=optimizer.state_dict(), rng=torch.get_rng_state(), recipe="trafficweaving train ...")
    return path


def edited(saved: Path, name: str, change) -> Path:
    """A copy of ``saved`` with ``change(payload)`` applied and a *correct* digest, so that the
    check under test (not the digest) is what refuses it."""
    payload = torch.load(saved, weights_only=True)
    change(payload)
    path = saved.with_name(name)
    write_payload(path, payload)
    return path


def set_tensor(name: str, value):
    def change(payload):
        payload["state_dict"][name] = value(payload["state_dict"][name]) if callable(value) else value
    return change


# ---------------------------------------------------------------- format and digest
@pytest.mark.slow
def test_round_trip_keeps_every_tensor_and_field(model, saved):
    loaded, payload = load_checkpoint(saved)
    assert payload["version"] == VERSION == 6 and payload[HASH_FIELD] == tensor_digest(payload)
    for name, tensor in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], tensor) and payload["state_dict"][name].dtype == tensor.dtype
    assert payload["step"] == 7 and payload["history"] == [(5, -1.5)] and payload["train_config"] == {"steps": 7}
    assert payload["config"] == model.config.to_dict() and payload["recipe"] == "trafficweaving train ..."
    assert torch.equal(payload["rng"], torch.load(saved, weights_only=True)["rng"])
    assert not loaded.training


def test_digest_covers_nested_tensors_names_dtypes_and_not_key_order(saved):
    payload = torch.load(saved, weights_only=True)
    digest = tensor_digest(payload)
    assert digest == payload[HASH_FIELD] and len(digest) == 64
    assert tensor_digest(dict(reversed(payload.items()))) == digest  # sorted keys, not insertion order
    moments = payload["optimizer"]["state"][0]
    original = moments["exp_avg"]
    moments["exp_avg"] = original.clone().add_(1.0)  # optimizer moments are covered, not only the weights
    assert tensor_digest(payload) != digest
    moments["exp_avg"] = original
    assert tensor_digest(payload) == digest
    state = payload["state_dict"]
    state["renamed"] = state.pop("decoder.bias")  # the name is part of the digest
    assert tensor_digest(payload) != digest
    state["decoder.bias"] = state.pop("renamed")
    state["feature_std"] = state["feature_std"].view(torch.int32)  # same bytes, other dtype
    assert tensor_digest(payload) != digest


def _tensor_data_offset(path: Path) -> tuple[int, int]:
    """(offset in the file, size) of the largest tensor's raw data inside a torch zip checkpoint."""
    with zipfile.ZipFile(path) as archive:
        info = max((i for i in archive.infolist() if "/data/" in i.filename), key=lambda i: i.file_size)
        assert info.compress_type == zipfile.ZIP_STORED
    with open(path, "rb") as f:
        f.seek(info.header_offset)
        header = f.read(30)
    name_length, extra_length = struct.unpack("<HH", header[26:30])
    return info.header_offset + 30 + name_length + extra_length, info.file_size


def test_a_flipped_byte_in_tensor_data_is_refused(saved):
    data = bytearray(saved.read_bytes())
    offset, size = _tensor_data_offset(saved)
    data[offset + size // 2] ^= 0x01  # the lowest mantissa bit of one weight: a finite, plausible value
    flipped = saved.with_name("flipped.pt")
    flipped.write_bytes(bytes(data))
    fails(flipped, r"flipped\.pt: tensor data does not match the checkpoint's SHA-256 \(the file is corrupted or was "
                   r"edited; expected a checkpoint as written by trafficweaving\)")
    with pytest.raises(InputError, match="SHA-256"):
        load_model(str(flipped))  # the --model path, too


def test_edited_tensors_without_a_new_digest_are_refused(saved):
    payload = torch.load(saved, weights_only=True)
    payload["state_dict"] = {k: v.to(torch.int64) for k, v in payload["state_dict"].items()}  # weights cast to int64
    torch.save(payload, saved.with_name("int.pt"))
    fails(saved.with_name("int.pt"), "tensor data does not match the checkpoint's SHA-256")


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.int64, torch.float64, torch.float16])
def test_weights_of_another_dtype_are_refused_even_with_a_valid_digest(saved, dtype):
    def cast(payload):
        payload["state_dict"] = {k: v.to(dtype) for k, v in payload["state_dict"].items()}
    path = edited(saved, "cast.pt", cast)
    message = fails(path, rf"tensor \S+ has dtype {str(dtype).removeprefix('torch.')} \(expected float32\)")
    assert "feature_mean" in message  # the first tensor of the state dict is named


@pytest.mark.slow
def test_non_finite_weights_are_refused(saved):
    nan = edited(saved, "nan.pt", set_tensor("decoder.bias", lambda t: t.clone().index_fill_(0, torch.tensor([3]), float("nan"))))
    fails(nan, r"nan\.pt: tensor decoder\.bias has NaN or infinite values \(expected finite weights\)")
    inf = edited(saved, "inf.pt", set_tensor("hold.log_sigma", torch.tensor([0.0, float("inf")])))
    fails(inf, "tensor hold.log_sigma has NaN or infinite values")


@pytest.mark.parametrize("name, value, expected", [
    ("feature_std", torch.tensor([1.0, 1.0, 0.0, 1.0, 1.0, 1.0]), "positive standard deviations"),
    ("label_std", torch.tensor([-0.5, 1.0]), "positive standard deviations"),
    ("latent_temperature", torch.tensor(-1.0), "a positive temperature"),
    ("output_scale", torch.tensor([1.0, 0.0]), "a positive scale"),
])
def test_non_positive_standard_deviations_and_calibration_are_refused(saved, name, value, expected):
    path = edited(saved, "bad.pt", set_tensor(name, value))
    fails(path, rf"bad\.pt: tensor {name} has a value -?[0-9.]+ <= 0 \(expected {expected}\)")


@pytest.mark.slow
def test_shapes_and_missing_or_extra_tensors_are_refused(saved):
    fails(edited(saved, "shape.pt", set_tensor("decoder.bias", torch.zeros(7))),
          r"tensor decoder\.bias has shape \[7\] \(expected \[512\]\)")
    fails(edited(saved, "missing.pt", lambda p: p["state_dict"].pop("decoder.bias")), "lacks tensor decoder.bias")
    fails(edited(saved, "extra.pt", set_tensor("spare", torch.zeros(1))), "has unexpected tensor spare")
    fails(edited(saved, "list.pt", set_tensor("decoder.bias", [0.0] * 512)), r"decoder\.bias is \[0\.0.* \(expected a tensor\)")
    fails(edited(saved, "nostate.pt", lambda p: p.__setitem__("state_dict", [1, 2])), "no state_dict dictionary")


@pytest.mark.parametrize("field, value, pattern", [
    ("decoder_units", "128", r"config field decoder_units is '128' \(expected an integer in 1\.\.4096\)"),
    ("decoder_units", 0, r"config field decoder_units is 0 \(expected an integer"),
    ("history_units", -32, r"config field history_units is -32 \(expected an integer"),
    ("components", True, r"config field components is True \(expected an integer"),
    ("components", 16.0, r"config field components is 16\.0 \(expected an integer"),
    ("p_z_hidden", 10**9, r"config field p_z_hidden is 1000000000 \(expected an integer in 1\.\.4096\)"),
    ("hold", 1, r"config field hold is 1 \(expected true or false\)"),
    ("dropout", 0.5, r"config has unknown field 'dropout' \(expected only \["),
    ("latent_vars", 40, r"config latent_classes \*\* latent_vars is 5\^40 \(expected at most 4096"),
])
def test_hand_edited_configs_are_refused(saved, field, value, pattern):
    path = edited(saved, "config.pt", lambda p: p["config"].__setitem__(field, value))
    fails(path, r"config\.pt: " + pattern)


def test_a_config_that_is_not_a_dictionary_is_refused(saved):
    fails(edited(saved, "config.pt", lambda p: p.__setitem__("config", "cvae")), "config.pt: checkpoint has no config dictionary")


@pytest.mark.parametrize("field, value, expected", [
    ("step", -1, "a non-negative integer"),
    ("step", "200", "a non-negative integer"),
    ("step", True, "a non-negative integer"),
    ("history", "[(5, -1.5)]", "a list of"),
    ("history", [(5, "x")], "a list of"),
    ("held_out_trials", ["3"], "a list of integer trial ids"),
    ("data_fingerprint", 12, "a string"),
    ("calibration", [2.0, 2.0], "a dictionary"),
    ("crossval", None, "a dictionary"),
])
def test_malformed_fields_that_commands_read_are_refused(saved, field, value, expected):
    path = edited(saved, "field.pt", lambda p: p.__setitem__(field, value))
    fails(path, rf"field\.pt: checkpoint field {field} is .* \(expected {expected}")


@pytest.mark.slow
def test_malformed_resume_state_is_refused(saved):
    fails(edited(saved, "tc.pt", lambda p: p["train_config"].__setitem__("batch_size", "32")),
          r"train_config field batch_size is '32' \(expected an integer")
    fails(edited(saved, "tc.pt", lambda p: p["train_config"].__setitem__("lr_initial", float("nan"))),
          r"train_config field lr_initial is nan \(expected a finite number")
    fails(edited(saved, "rng.pt", lambda p: p.__setitem__("rng", torch.zeros(3, dtype=torch.uint8))),
          "checkpoint field rng is not a torch CPU RNG state")
    fails(edited(saved, "opt.pt", lambda p: p.__setitem__("optimizer", {"state": {}})), "checkpoint field optimizer is malformed")
    fails(edited(saved, "opt.pt", lambda p: p["optimizer"]["state"][0].__setitem__("exp_avg_sq", torch.tensor(float("nan")))),
          "optimizer state 0 is malformed or not finite")
    fails(edited(saved, "opt.pt", lambda p: p["optimizer"]["param_groups"][0]["params"].pop()),
          r"optimizer state covers \d+ parameters \(expected the model's \d+ trainable ones\)")


@pytest.mark.slow
def test_older_versions_load_with_their_density(model, saved):
    """Before version 4 the output scale was one number for both directions, and in version 2 it
    also widened the hold modes: such files load with the scale in both directions and (version 2)
    folded into the hold widths, so every hold and GMM width is what it was."""
    def as_version(version):
        def change(payload):
            payload["version"] = version
            payload["state_dict"]["output_scale"] = torch.tensor(2.0)
        return change
    v2, _ = load_checkpoint(edited(saved, "v2.pt", as_version(2)))
    v3, _ = load_checkpoint(edited(saved, "v3.pt", as_version(3)))
    assert VERSION == 6 and v2.output_scale.tolist() == v3.output_scale.tolist() == [2.0, 2.0]
    torch.testing.assert_close(v2.hold.widths(), model.hold.widths() + np.log(2.0))
    torch.testing.assert_close(v3.hold.widths(), model.hold.widths())
    fails(edited(saved, "v4.pt", set_tensor("output_scale", torch.tensor(2.0))), r"output_scale has shape \[\] \(expected \[2\]\)")


def test_version_1_and_missing_digests_are_refused(saved):
    payload = torch.load(saved, weights_only=True)
    old = {k: v for k, v in payload.items() if k != HASH_FIELD} | {"version": 1}
    torch.save(old, saved.with_name("v1.pt"))
    fails(saved.with_name("v1.pt"), r"v1\.pt: checkpoint version 1 \(expected version 2, 3, 4, 5, 6, which carry a SHA-256")
    torch.save({**old, "version": 2}, saved.with_name("nohash.pt"))
    fails(saved.with_name("nohash.pt"), r"nohash\.pt: checkpoint has no valid tensor_sha256")
    torch.save({**payload, HASH_FIELD: "0" * 64}, saved.with_name("zero.pt"))
    fails(saved.with_name("zero.pt"), "does not match the checkpoint's SHA-256")


def test_unreadable_files_are_refused(saved, tmp_path):
    data = saved.read_bytes()
    (tmp_path / "truncated.pt").write_bytes(data[: len(data) // 2])
    fails(tmp_path / "truncated.pt", r"truncated\.pt: not a readable checkpoint")
    (tmp_path / "random.pt").write_bytes(np.random.default_rng(0).bytes(4096))
    fails(tmp_path / "random.pt", r"random\.pt: not a readable checkpoint")
    (tmp_path / "folder.pt").mkdir()
    fails(tmp_path / "folder.pt", r"folder\.pt: is a folder")
    fails(tmp_path / "none.pt", r"none\.pt: no such file")
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    fails(tmp_path / "other.pt", "not a trafficweaving model checkpoint")
    for loader in (read_checkpoint, lambda p: load_model(str(p))):
        fails(tmp_path / "random.pt", "not a readable checkpoint", loader=loader)


def test_save_recomputes_given_reserved_fields_and_export_keeps_a_valid_digest(model, saved, tmp_path):
    payload = read_checkpoint(saved)  # re-saving a read payload (as `calibrate` does) passes its old digest along
    kept = {k: v for k, v in payload.items() if k not in ("format", "version", "config", "state_dict")}
    save_checkpoint(tmp_path / "again.pt", model.set_calibration(2.0, 1.5), **kept)
    again, again_payload = load_checkpoint(tmp_path / "again.pt")
    assert again.output_scale.tolist() == [1.5, 1.5] and again_payload[HASH_FIELD] != payload[HASH_FIELD]
    export_checkpoint(saved, tmp_path / "export.pt", data_command="trafficweaving generate")
    exported = read_checkpoint(tmp_path / "export.pt")
    assert "optimizer" not in exported and "rng" not in exported and exported["data_command"] == "trafficweaving generate"
    assert exported[HASH_FIELD] == tensor_digest(exported)


@pytest.mark.parametrize("name", ["default", "simulated-real", "driver", "fast"])
def test_the_shipped_models_load_and_verify(name):
    model, payload = load_checkpoint(shipped_model_path(name))
    assert model.config.robot_future == ("guess" if name == "driver" else "recorded")
    assert payload["version"] in READABLE_VERSIONS and payload[HASH_FIELD] == tensor_digest(payload)
    assert model.config.hold and all(v.dtype == torch.float32 for v in payload["state_dict"].values())
    sizes = (16, 8) if name == "fast" else (128, 16)  # the fast model: the default's decoder distilled (docs/fast_model.md)
    assert (model.config.decoder_units, model.config.components) == sizes
    if name != "driver":  # the driver model is not calibrated (docs/realism.md)
        scale = payload["calibration"]["output_scale"]  # {"x", "y"}, or one number in files before version 4
        assert model.output_scale.tolist() == pytest.approx(list(scale.values()) if isinstance(scale, dict) else [scale] * 2)


def test_a_corrupted_model_fails_the_cli_in_one_line(saved, tmp_path, capsys):
    from trafficweaving.cli import main

    assert main(["generate", "--trials", "2", "--seed", "1", "--out", str(tmp_path / "d.parquet"), "--json"]) == 0
    data = bytearray(saved.read_bytes())
    offset, size = _tensor_data_offset(saved)
    data[offset + size // 3] ^= 0x80
    (tmp_path / "bad.pt").write_bytes(bytes(data))
    capsys.readouterr()
    code = main(["evaluate", "--model", str(tmp_path / "bad.pt"), "--data", str(tmp_path / "d.parquet"), "--json"])
    err = capsys.readouterr().err
    assert code == 2 and "bad.pt: tensor data does not match" in err and err.count("\n") == 1


# ---------------------------------------------------------------- the authors' weights
@pytest.fixture(scope="module")
def authors_weights(authors_model_dir) -> dict[str, np.ndarray]:
    with np.load(authors_model_dir / "weights.npz") as npz:
        return {k: npz[k] for k in npz.files}


def write_npz(path: Path, weights: dict) -> Path:
    np.savez(path, **weights)
    return path


KERNEL = "decoder/p_y_xz/rnn/mu_projection/kernel"
STD = "features_standardization/train_std"


def test_authors_weights_load_and_float64_copies_agree(authors_model_dir, authors_weights, tmp_path):
    reference = load_authors_model(authors_model_dir / "weights.npz")
    wide = write_npz(tmp_path / "w64.npz", {k: v.astype(np.float64) if v.dtype == np.float32 else v
                                            for k, v in authors_weights.items()})
    for name, tensor in load_authors_model(wide).state_dict().items():
        assert torch.equal(tensor, reference.state_dict()[name]), name


def test_authors_weights_with_bad_values_are_refused(authors_weights, tmp_path):
    load = load_authors_model
    nan = {**authors_weights, KERNEL: np.where(np.arange(authors_weights[KERNEL].size).reshape(authors_weights[KERNEL].shape) == 5,
                                               np.nan, authors_weights[KERNEL]).astype(np.float32)}
    fails(write_npz(tmp_path / "nan.npz", nan), rf"nan\.npz: tensor {KERNEL} has NaN or infinite values", loader=load)
    huge = {**authors_weights, KERNEL: np.full(authors_weights[KERNEL].shape, 1e300)}  # float64 overflows float32
    fails(write_npz(tmp_path / "huge.npz", huge), "has NaN or infinite values", loader=load)
    zero = {**authors_weights, STD: np.zeros(6, np.float32)}
    fails(write_npz(tmp_path / "zero.npz", zero), rf"zero\.npz: tensor {STD} has a value 0 <= 0", loader=load)
    ints = {**authors_weights, KERNEL: authors_weights[KERNEL].astype(np.int64)}
    fails(write_npz(tmp_path / "int.npz", ints), rf"int\.npz: tensor {KERNEL} has dtype int64 \(expected floating", loader=load)
    text = {**authors_weights, KERNEL: np.array(["0.1"] * 4)}
    fails(write_npz(tmp_path / "text.npz", text), rf"text\.npz: tensor {KERNEL} has dtype <U3", loader=load)


def test_authors_weights_with_missing_misshapen_or_extra_arrays_are_refused(authors_weights, tmp_path):
    load = load_authors_model
    missing = {k: v for k, v in authors_weights.items() if k != KERNEL}
    fails(write_npz(tmp_path / "missing.npz", missing), rf"missing\.npz: missing tensor {KERNEL}", loader=load)
    shape = {**authors_weights, KERNEL: authors_weights[KERNEL].T}
    fails(write_npz(tmp_path / "shape.npz", shape), rf"shape\.npz: tensor {KERNEL} has shape \[32, 128\] \(expected \[128, 32\]\)",
          loader=load)
    lstm = "car_history_rnn/rnn/multi_rnn_cell/cell_0/layer_norm_basic_lstm_cell/kernel"
    flat = {**authors_weights, lstm: authors_weights[lstm].reshape(-1)}
    fails(write_npz(tmp_path / "flat.npz", flat), rf"tensor {lstm} has shape \[5632\] \(expected \[44, 128\]\)", loader=load)
    scalar = {**authors_weights, lstm: np.float32(1.0)}
    fails(write_npz(tmp_path / "scalar.npz", scalar), r"has shape \[\] \(expected \[44, 128\]\)", loader=load)
    extra = {**authors_weights, "surplus": np.zeros(1, np.float32)}
    fails(write_npz(tmp_path / "extra.npz", extra), r"extra\.npz: unexpected tensor surplus", loader=load)


def test_unreadable_authors_files_are_refused(tmp_path):
    load = load_authors_model
    (tmp_path / "random.npz").write_bytes(np.random.default_rng(1).bytes(2048))
    fails(tmp_path / "random.npz", r"random\.npz: not a readable \.npz file", loader=load)
    np.save(tmp_path / "single.npy", np.zeros(3))
    fails(tmp_path / "single.npy", r"single\.npy: not a readable \.npz file", loader=load)
    np.savez(tmp_path / "objects.npz", a=np.array([{"x": 1}], dtype=object))
    fails(tmp_path / "objects.npz", r"objects\.npz: not a readable \.npz file", loader=load)
    (tmp_path / "folder.npz").mkdir()
    fails(tmp_path / "folder.npz", r"folder\.npz: is a folder", loader=load)
    fails(tmp_path / "none.npz", r"none\.npz: no such file", loader=load)
    with pytest.raises(InputError, match="none.npz: no such file"):
        load_model("authors:" + str(tmp_path / "none.npz"))


# ---------------------------------------------------------------- devices
@pytest.mark.parametrize("name", ["meta", "mps", "xla", "cuda:99", "", "CPU", "cpu:0", "cuda:-1", "cuda:0x1", " cuda"])
def test_unknown_or_absent_devices_are_refused(name):
    with pytest.raises(InputError, match=r"^--device .*\(expected auto(, cpu, cuda or cuda:N with N < \d+| or cpu; cuda and cuda:N need CUDA)") as info:
        choose_device(name)
    assert repr(name) in str(info.value) and "\n" not in str(info.value)


def test_known_devices_are_accepted():
    assert choose_device("cpu") == torch.device("cpu")
    assert choose_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if torch.cuda.is_available():
        assert choose_device("cuda") == torch.device("cuda")
        assert choose_device(f"cuda:{torch.cuda.device_count() - 1}").index == torch.cuda.device_count() - 1
    else:
        with pytest.raises(InputError, match=r"--device 'cuda': CUDA is not available"):
            choose_device("cuda")
        with pytest.raises(InputError, match=r"--device 'cuda:0': CUDA is not available"):
            choose_device("cuda:0")
