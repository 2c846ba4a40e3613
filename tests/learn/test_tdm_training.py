"""The online TDM training loop: budgets, validation metrics, early stopping, soft labels."""
import numpy as np
import pytest
import torch

from skinsafe.core.learn.tdm_training import FitConfig, TDMTrainer, auc, calibration
from skinsafe.core.safety.tdm import TactileDangerModel

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_auc_and_calibration_against_hand_values():
    assert auc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == pytest.approx(0.75)
    assert auc([0.5, 0.5], [0, 1]) == pytest.approx(0.5)  # ties count half
    assert auc([0.1, 0.2], [0, 0]) is None
    c = calibration([0.05, 0.05, 0.95, 0.95], [0, 0, 1, 1])
    assert c["ece"] == pytest.approx(0.05) and c["brier"] == pytest.approx(0.0025)


def _data(rng, n):
    """Danger on taxel 0 exactly when x > 0.5 and the action is 1 (of 2)."""
    s = rng.uniform(0, 1, (n, 2)).astype(np.float32)
    a = rng.integers(0, 2, n)
    d = np.zeros((n, 3), np.float32)
    d[:, 0] = (s[:, 0] > 0.5) & (a == 1)
    return s, np.eye(2, dtype=np.float32)[a], d


def test_refits_learn_a_rule_and_report_validation_metrics():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    t = TDMTrainer(TactileDangerModel(2, 2, 3, (32, 32)), FitConfig(steps=300, eval_every=25, patience=100), seed=0)
    t.add(*_data(rng, 600))
    first = t.fit()
    assert first["steps"] == 300 and first["val_samples"] == int(t.val[: t.n].sum()) > 60
    for _ in range(3):
        rec = t.fit()
    assert rec["auc"] > 0.97 and rec["ece"] < 0.1 and rec["val_loss"] < first["val_loss"]
    assert len(t.history) == 4 and t.seconds > 0


def test_early_stopping_ends_a_converged_fit_within_patience():
    torch.manual_seed(1)
    rng = np.random.default_rng(1)
    t = TDMTrainer(TactileDangerModel(2, 2, 3, (32, 32)), FitConfig(steps=2000, eval_every=10, patience=2), seed=1)
    t.add(*_data(rng, 400))
    for _ in range(4):
        t.fit()
    assert t.history[-1]["steps"] < 2000  # stopped early, best weights kept
    assert t.history[-1]["val_loss"] <= min(r["val_loss"] for r in t.history[:-1]) + 0.02


def test_soft_labels_and_bad_input():
    t = TDMTrainer(TactileDangerModel(2, 2, 3, (8,)), seed=0)
    t.add(np.zeros((4, 2)), np.eye(2)[[0, 1, 0, 1]], np.full((4, 3), 0.25))  # soft targets are fine
    assert t.n == 4
    with pytest.raises(ValueError, match="dangers in \\[0, 1\\]"):
        t.add(np.zeros((1, 2)), np.eye(2)[[0]], np.full((1, 3), 1.5))
    with pytest.raises(ValueError, match="do not match the model"):
        t.add(np.zeros((1, 5)), np.eye(2)[[0]], np.zeros((1, 3)))


def test_a_focused_fit_learns_the_one_new_contact():
    """One contact among 2,000 safe samples: a uniform 100-step refit sees it a handful of times and its
    validation-based early stop can throw it away (p = 0.0002 after it); a fit with the contact in every
    batch raises it ~1,000-fold (0.19) without overriding the 2,000 safe samples around it."""
    p = {}
    for focus in (False, True):
        torch.manual_seed(0)
        tr = TDMTrainer(TactileDangerModel(2, 2, 3, (16, 16)), FitConfig(steps=100, batch_size=32, val_fraction=0.1), seed=1)
        rng = np.random.default_rng(0)
        tr.add(rng.uniform(-1, 1, (2000, 2)), np.eye(2)[rng.integers(2, size=2000)], np.zeros((2000, 3)))
        tr.fit()
        s, a = np.array([[0.5, 0.5]]), np.array([[1.0, 0.0]])
        tr.add(s, a, np.array([[0.0, 1.0, 0.0]]))
        tr.val[tr.last] = False  # the contact landed in the training split
        tr.fit(focus=[tr.last] if focus else ())
        with torch.no_grad():
            p[focus] = float(torch.sigmoid(tr.model(torch.as_tensor(s, dtype=torch.float32), torch.as_tensor(a, dtype=torch.float32)))[0, 1])
    assert p[True] > 0.1 > 100 * p[False]
