"""The tactile danger model: shapes, checkpoints, bad input, and learning contacts in the maze."""
import numpy as np
import pytest
import torch

from skinsafe.core.learn.maze_env import MazeEnv, MazeFeatures
from skinsafe.core.safety.tdm import TactileDangerModel, load_tdm, one_hot, save_tdm, train_tdm

pytestmark = pytest.mark.usefixtures("one_torch_thread")


class Evil:
    """An arbitrary pickled object: weights_only loading must refuse it."""


def test_shapes_and_10k_taxel_head_is_one_linear_layer():
    m = TactileDangerModel(6, 4, 10000, hidden=(128, 128))
    with torch.no_grad():
        out = m(torch.zeros(3, 6), one_hot([0, 1, 3], 4))
    assert out.shape == (3, 10000)
    assert float(torch.sigmoid(out).mean()) < 0.05  # rare-contact prior (head bias at p = 1%)
    n_params = sum(p.numel() for p in m.parameters())
    assert n_params == (10 * 128 + 128) + (128 * 128 + 128) + (128 * 10000 + 10000)


def test_checkpoint_roundtrip_weights_only_and_refuses_bad_files(tmp_path):
    torch.manual_seed(0)
    m = TactileDangerModel(4, 4, 16, hidden=(32,))
    path = tmp_path / "tdm.pt"
    save_tdm(m, path)
    m2 = load_tdm(path)
    s, a = torch.randn(5, 4), one_hot([0, 1, 2, 3, 0], 4)
    assert torch.equal(m(s, a), m2(s, a))
    assert [p.name for p in tmp_path.iterdir()] == ["tdm.pt"]  # no temporary left behind
    torch.save({"schema_version": 99, "config": {}, "state_dict": {}}, tmp_path / "new.pt")
    with pytest.raises(ValueError, match="schema_version"):
        load_tdm(tmp_path / "new.pt")
    torch.save({"obj": Evil()}, tmp_path / "evil.pt")
    with pytest.raises(ValueError, match="weights_only"):
        load_tdm(tmp_path / "evil.pt")


def test_train_rejects_bad_input_clearly():
    m = TactileDangerModel(4, 4, 16)
    with pytest.raises(ValueError, match="'dangers' has 8 columns"):
        train_tdm(m, np.zeros((5, 4)), one_hot([0] * 5, 4), np.zeros((5, 8)), progress=False)
    with pytest.raises(ValueError, match="'actions' has 3 rows"):
        train_tdm(m, np.zeros((5, 4)), np.zeros((3, 4)), np.zeros((5, 16)), progress=False)
    with pytest.raises(ValueError, match="NaN"):
        train_tdm(m, np.full((5, 4), np.nan), np.zeros((5, 4)), np.zeros((5, 16)), progress=False)
    with pytest.raises(ValueError, match="0/1"):
        train_tdm(m, np.zeros((5, 4)), np.zeros((5, 4)), np.full((5, 16), 0.5), progress=False)


def test_training_is_reproducible_with_a_seed():
    rng = np.random.default_rng(0)
    s, a, d = rng.normal(size=(64, 4)), one_hot(rng.integers(4, size=64), 4), (rng.random((64, 16)) < 0.2)
    out = []
    for _ in range(2):
        torch.manual_seed(1)
        m = TactileDangerModel(4, 4, 16, hidden=(16,))
        out.append(train_tdm(m, s, a, d.astype(float), epochs=3, seed=5, progress=False)["loss"])
    assert out[0] == out[1] and out[0][-1] < out[0][0]


def _maze_data(env, feats, n, rng):
    S, A, D = [], [], []
    obs, _ = env.reset(seed=0)
    for _ in range(n):
        a = int(rng.integers(4))
        nxt, r, term, trunc, info = env.step(a)
        S.append(feats(obs)[0]), A.append(a), D.append(info["taxel_danger"].astype(float))
        obs = nxt
        if term or trunc:
            obs, _ = env.reset()
    return np.stack(S), np.array(A), np.stack(D)


def auc(scores, labels):
    order = np.argsort(scores)
    ranks = np.empty(len(scores))
    ranks[order] = np.arange(1, len(scores) + 1)
    pos = labels.astype(bool)
    return (ranks[pos].sum() - pos.sum() * (pos.sum() + 1) / 2) / (pos.sum() * (~pos).sum())


def test_tdm_predicts_held_out_maze_contacts_better_than_chance():
    rng = np.random.default_rng(0)
    env = MazeEnv(max_steps=60)
    feats = MazeFeatures(env.walls)
    S, A, D = _maze_data(env, feats, 700, rng)
    tr, te = slice(0, 450), slice(450, None)
    torch.manual_seed(0)
    model = TactileDangerModel(feats.dim, 4, env.n_taxels, hidden=(64, 64))
    hist = train_tdm(model, S[tr], one_hot(A[tr], 4), D[tr], epochs=40, lr=3e-3, batch_size=64, seed=0, progress=False)
    assert hist["loss"][-1] < hist["loss"][0]
    with torch.no_grad():
        logits = model(torch.as_tensor(S[te]), one_hot(A[te], 4)).numpy()
    from skinsafe.core.safety.danger import total_danger
    any_contact = D[te].any(1)
    assert 0.05 < any_contact.mean() < 0.6  # both classes present on held-out data
    score = auc(total_danger(logits), any_contact)
    assert score > 0.85, score  # chance is 0.5
    # Per taxel: the front taxel (0) on forward moves.
    fwd = A[te] == 0
    assert auc(logits[fwd, 0], D[te][fwd, 0]) > 0.7
