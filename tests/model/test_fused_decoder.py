"""The fused decoder (model/fused_decoder.py): its steps equal the fast sampler; int8 weights per row."""

import pytest
import torch

from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.fused_decoder import INT8_RANGE, FusedDecoder, quantize_rows
from trafficweaving.model.sampler import BatchedRollout


@pytest.mark.parametrize("variant, calibration", [("cvae", None), ("lstm", None), ("cvae-hold", None),
                                                  ("cvae-hold", (3.0, 1.7))])
def test_fused_decoder_steps_equal_the_fast_sampler_given_the_same_random_numbers(variant, calibration):
    """The fused steps of precision int8, with its weights left unquantised, are the
    batched sampler's decoder (float64, run eagerly)."""
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant)).double().eval()
    if calibration:
        model.set_calibration(*calibration)
    fast = BatchedRollout(model)
    fused = FusedDecoder(fast.w_step, fast.latent_gates, fast.latent_init, fast.w_head, fast.head_bias, fast.output_scale,
                         fast.hold_sigma if model.config.hold else None, fast.modes, fast.components,
                         quantize=False, compiled=False)
    context = fast.encode(torch.randn(9, 12, dtype=torch.float64), torch.randn(6, 15, 6, dtype=torch.float64),
                          torch.randn(2, dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    cand, z = torch.randint(6, (40,), generator=g), torch.randint(len(model.latent_onehots), (40,), generator=g)
    uniform, normal = torch.rand(40, 15, generator=g, dtype=torch.float64), torch.randn(40, 15, 2, generator=g, dtype=torch.float64)
    ours = fused.decode(context, cand, z, context["present_action"], uniform, normal)
    reference = fast.decode_rows(context, cand, z, uniform, normal)
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-10)


def test_int8_weights_round_trip_within_half_a_step():
    w = torch.randn(64, 32) * torch.logspace(-3, 1, 64)[:, None]  # rows of very different sizes
    codes, scale = quantize_rows(w)
    assert codes.dtype == torch.int8 and codes.abs().max() == INT8_RANGE
    assert ((codes * scale - w).abs() <= scale / 2 * (1 + 1e-6)).all()
