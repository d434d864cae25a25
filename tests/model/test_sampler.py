"""The planner's fast sampler (model/sampler.py) equals the model's own sampling, given the same random numbers."""

import pytest
import torch

from trafficweaving.model.cvae import CVAE, CVAEConfig
from trafficweaving.model.sampler import MIN_CHUNK_ROWS, BatchedRollout, chunk_rows_for


@pytest.mark.parametrize("variant, calibration", [("cvae", None), ("mixture-lstm", None), ("lstm", None),
                                                  ("cvae-hold", None), ("cvae-hold", (3.0, 1.7))])
def test_fast_sampler_equals_the_models_sampling_given_the_same_random_numbers(variant, calibration):
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant(variant)).double().eval()
    if calibration:
        model.set_calibration(*calibration)
    history = torch.randn(9, 12, dtype=torch.float64)
    futures = torch.randn(6, 15, 6, dtype=torch.float64)
    present = torch.randn(2, dtype=torch.float64)  # the human's present action
    fast = BatchedRollout(model, chunk_rows=5)  # chunks that split candidates
    context = fast.encode(history, futures, present)
    g = torch.Generator().manual_seed(1)
    latents = fast.sample_latents(context, 4, g)
    noise = (torch.rand(4, 6, 15, generator=g, dtype=torch.float64), torch.randn(4, 6, 15, 2, generator=g, dtype=torch.float64))
    ours = fast.sample(context, latents, noise=noise)
    with torch.no_grad():
        x = torch.cat([model.encode_history(history[None], torch.tensor([8])).expand(6, -1),
                       model.encode_robot_future(futures, history[-1, :6].expand(6, -1))], -1)
        zx = torch.cat([model.latent_onehots[latents], x.expand(4, -1, -1)], -1)
        robot_inputs = torch.cat([history[-1, :6].expand(6, 1, -1), futures[:, :-1]], 1)
        reference = model.sample_actions(zx, robot_inputs, present.expand(6, -1), noise=noise)
    torch.testing.assert_close(ours, reference, rtol=0, atol=1e-10)


def test_chunks_grow_for_narrow_decoders_and_are_the_same_samples():
    assert chunk_rows_for(128) == MIN_CHUNK_ROWS  # the paper's decoder
    assert chunk_rows_for(32) == 2 * MIN_CHUNK_ROWS and chunk_rows_for(512) == MIN_CHUNK_ROWS
    torch.manual_seed(0)
    model = CVAE(CVAEConfig.variant("cvae-hold", decoder_units=32)).double().eval()
    assert BatchedRollout(model).chunk_rows == chunk_rows_for(32)
    history, futures = torch.randn(9, 12, dtype=torch.float64), torch.randn(3, 15, 6, dtype=torch.float64)
    present = torch.zeros(2, dtype=torch.float64)
    samples = []
    for chunk_rows in (None, 7):
        rollout = BatchedRollout(model, chunk_rows=chunk_rows)
        context = rollout.encode(history, futures, present)
        samples.append(rollout.sample(context, rollout.sample_latents(context, 5, torch.Generator().manual_seed(1)),
                                      generator=torch.Generator().manual_seed(2)))
    torch.testing.assert_close(samples[0], samples[1], rtol=0, atol=1e-12)
