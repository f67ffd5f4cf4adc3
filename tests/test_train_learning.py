"""The learning test: a tiny DualFlow trained on synthetic duets really reacts to the actor.

A narrow model (2 blocks, width 64, x0 prediction) is trained for 400 steps on synthetic
duets of all four follower rules (reactive task, 1 s windows, flow loss, training times
t = sigmoid(N(-0.8, 0.8)) shifted towards the noise end), then generates the
reactor of 32 held-out clips (seeds never seen in training) with 10 Euler steps. Its mean
per-joint position error to the rule-generated follower must be clearly lower than

* the same model with the actor masked out (its features replaced by the training mean), and
* a static pose (the training set's mean reactor pose, the best constant pose).

The figures are printed (``pytest -s``); the slow mark keeps it out of the default run.
"""

from __future__ import annotations

import pytest

from dualflow.evaluation import reactor_errors
from dualflow.train import Trainer, load_train_config

LEARNING_RUN = [
    "preset=tiny",
    "model.width=64",
    "model.ff_dim=128",
    "model.n_heads=4",
    "model.prediction=x0",
    "data.n_clips=256",
    "data.val_clips=32",
    "data.frames=30",
    "steps=400",
    "batch_size=16",
    "lr=1e-3",
    "warmup_steps=20",
    "ema_decay=0",
    "reactive_prob=1.0",
    "losses=flow",
    "time_sampler=logit_normal",
    "time_mean=-0.8",
    "time_std=0.8",
    "threads=1",
    "progress=false",
    "ckpt_every=0",
    "log_every=50",
    "seed=0",
]


@pytest.mark.slow
def test_tiny_model_reacts_to_the_actor(tmp_path):
    trainer = Trainer(load_train_config(None, LEARNING_RUN + [f"out_dir={tmp_path}"]))
    trainer.run()
    errors = reactor_errors(trainer.model, trainer.val_set, trainer.train_set, steps=10)
    print(errors.summary())
    assert errors.model < 0.75 * errors.actor_masked, errors.summary()
    assert errors.model < 0.5 * errors.static_pose, errors.summary()
