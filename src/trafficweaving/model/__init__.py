"""The human model: the paper's CVAE of the human driver's next 15 accelerations (§III–IV), how
it is trained, scored, stored and loaded (docs/model.md).

Modules, bottom up: :mod:`.lstm`, :mod:`.gmm` (the parts) and :mod:`.cvae` (the model, its four
variants of Fig. 3 and ``cvae-hold``); :mod:`.mixture` (mixtures of models); :mod:`.exemplars`
(prediction instances from trials); :mod:`.sampler`, :mod:`.fused_decoder`, :mod:`.predictor`
(fast sampling for the planner) and :mod:`.constant_velocity` (the baseline human);
:mod:`.evaluate`, :mod:`.metrics` (NLL, coverage, displacement errors); :mod:`.train_config`,
:mod:`.checkpoint` (the file format), :mod:`.authors` (the authors' weights import);
:mod:`.spec` (the ``--model`` grammar), :mod:`.registry` (shipped models, loading a spec),
:mod:`.device` (``--device``); :mod:`.train` (training, fine-tuning), :mod:`.crossval`,
:mod:`.calibrate` (choices made out-of-fold) and :mod:`.workflows` (``mix``, ``calibrate``).

Nothing is imported here, so importing one module does not import them all.
"""
