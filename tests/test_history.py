import warnings

import gymnasium as gym
import numpy as np
import pytest

from sb3_pevfa.pevfa.history import PolicyHistory

OBS = gym.spaces.Box(-1, 1, (3,), np.float32)
ACT = gym.spaces.Discrete(2)


def _record(value: float, n_params=5, n_pairs=4, code_dim=0):
    return {
        "params": np.full(n_params, value, np.float32),
        "states": np.full((n_pairs, 3), value, np.float32),
        "actions": np.zeros((n_pairs, 1), np.float32),
        "codes": np.full(code_dim, value, np.float32),
    }


def _fill(history: PolicyHistory, n_policies: int, samples_per_policy: int) -> None:
    for i in range(n_policies):
        pid = history.add_record(_record(i), n_updates=i, num_timesteps=i * samples_per_policy)
        obs = np.full((samples_per_policy, 3), i, np.float32)
        history.add_samples(obs, np.full(samples_per_policy, i), pid)


def test_bounds_and_fifo_order():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, buffer_size=2500, max_policies=100, seed=0)
    _fill(history, 10, 1000)
    assert history.n_samples == 2500 and history.n_policies == 10
    obs, targets, ids = history.samples()
    # the oldest samples went first: half of policy 7, then policies 8 and 9
    assert np.array_equal(np.unique(ids), [7, 8, 9]) and (ids == 7).sum() == 500
    assert np.array_equal(obs[:, 0], targets) and np.array_equal(targets, ids.astype(np.float32))
    assert history.nbytes > 0 and "policies=10" in repr(history)


def test_policy_bound_evicts_its_samples():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, buffer_size=10_000, max_policies=3, seed=0)
    _fill(history, 5, 100)
    assert history.policy_ids == [2, 3, 4]
    _, _, ids = history.samples()
    assert set(ids.tolist()) == {2, 3, 4} and history.n_samples == 300
    assert history.record_info(4) == {"n_updates": 4, "num_timesteps": 400}
    np.testing.assert_array_equal(history.records([4, 2])["params"][:, 0], [4, 2])
    # only the fields a representation reads are stacked
    params_only = history.records([4, 2], fields=("params",))
    assert params_only["params"].shape == (2, 5) and params_only["states"].shape == (2, 0, 3)


def test_sampling_excludes_current_policy_and_is_seeded():
    def draw(seed):
        history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=seed)
        _fill(history, 4, 50)
        return [history.sample(32, exclude_policy=3) for _ in range(20)]

    batches = draw(0)
    assert all(3 not in ids for _, _, ids in batches)
    assert all(np.array_equal(a[2], b[2]) for a, b in zip(batches, draw(0)))
    assert not all(np.array_equal(a[2], b[2]) for a, b in zip(batches, draw(1)))
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4)
    _fill(history, 1, 10)
    assert history.sample(8, exclude_policy=0) is None
    assert history.sample(8)[0].shape == (8, 3)


def test_dict_observations_and_save_load_roundtrip(tmp_path):
    obs_space = gym.spaces.Dict({"a": gym.spaces.Box(-1, 1, (2,)), "img": gym.spaces.Box(0, 255, (4, 4, 1), np.uint8)})
    history = PolicyHistory(obs_space, ACT, 5, n_state_action_pairs=0, code_dim=2, seed=0, buffer_size=150, representation="x")
    for i in range(3):
        record = _record(i, n_pairs=0, code_dim=2)
        record["states"] = np.zeros((0, 2 + 16), np.float32)
        pid = history.add_record(record, n_updates=10 * i, num_timesteps=60 * i)
        history.add_samples({"a": np.full((2, 30, 2), i), "img": np.full((2, 30, 4, 4, 1), i)}, np.full((2, 30), i), pid)
        history.update_record_info(pid, episode_return=0.5 + i)
    assert history.n_samples == 150
    obs, _, _ = history.sample(10)
    assert obs["img"].dtype == np.uint8 and obs["img"].shape == (10, 4, 4, 1)
    history.save(tmp_path / "hist")
    loaded = PolicyHistory(
        obs_space, ACT, 5, n_state_action_pairs=0, code_dim=2, seed=123, buffer_size=150, representation="x"
    )
    loaded.load(tmp_path / "hist")
    assert loaded.policy_ids == history.policy_ids
    assert [loaded.record_info(i) for i in range(3)] == [
        {"n_updates": 10 * i, "num_timesteps": 60 * i, "episode_return": 0.5 + i} for i in range(3)
    ]
    assert [loaded.sample_count(i) for i in range(3)] == [history.sample_count(i) for i in range(3)]
    for a, b in zip(history.samples(), loaded.samples()):
        if isinstance(a, dict):
            assert all(np.array_equal(a[k], b[k]) for k in a)
        else:
            assert np.array_equal(a, b)
    # the RNG state travels with the file
    assert np.array_equal(history.sample(16)[2], loaded.sample(16)[2])
    # policy ids continue after a load
    record = {k: v[0] for k, v in history.records([2]).items()}
    assert history.add_record(record) == 3 and loaded.add_record(record) == 3


def test_load_mismatch_is_a_clear_error(tmp_path):
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, representation="opr")
    _fill(history, 2, 10)
    history.save(tmp_path / "h.npz")
    with pytest.raises(ValueError, match="representation: file has 'opr', model expects 'spr'"):
        PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, representation="spr").load(tmp_path / "h.npz")
    other_obs = gym.spaces.Box(-1, 1, (4,), np.float32)
    with pytest.raises(ValueError, match="observation_shapes"):
        PolicyHistory(other_obs, ACT, 5, n_state_action_pairs=4, representation="opr").load(tmp_path / "h.npz")
    with pytest.raises(ValueError, match="n_params"):
        PolicyHistory(OBS, ACT, 6, n_state_action_pairs=4, representation="opr").load(tmp_path / "h.npz")


def test_bad_records_and_arguments():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4)
    with pytest.raises(ValueError, match="params"):
        history.add_record(_record(0, n_params=6))
    with pytest.raises(KeyError):
        history.add_samples(np.zeros((2, 3)), np.zeros(2), 0)
    first = history.add_record(_record(0))
    history.add_record(_record(1))
    with pytest.raises(ValueError, match="latest"):
        history.add_samples(np.zeros((2, 3)), np.zeros(2), first)
    for kwargs in ({"buffer_size": 0}, {"max_policies": -1}):
        with pytest.raises(ValueError, match="positive"):
            PolicyHistory(OBS, ACT, 5, **kwargs)


def test_float64_observations_are_stored_as_float32():
    history = PolicyHistory(gym.spaces.Box(-1, 1, (3,), np.float64), ACT, 5, n_state_action_pairs=4)
    pid = history.add_record(_record(0))
    history.add_samples(np.ones((10, 3), np.float64), np.zeros(10), pid)
    assert history.samples()[0].dtype == np.float32


def test_a_failed_load_leaves_the_history_as_it_was(tmp_path):
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, representation="opr", seed=0)
    _fill(history, 3, 10)
    history.save(tmp_path / "good")
    other = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, representation="spr")
    _fill(other, 1, 10)  # another representation than `history`
    other.save(tmp_path / "other")
    (tmp_path / "broken.npz").write_bytes((tmp_path / "good.npz").read_bytes()[:200])
    with np.load(tmp_path / "good.npz") as archive:  # the right signature, but an array missing: found while reading
        np.savez(tmp_path / "incomplete.npz", **{k: archive[k] for k in archive.files if k != "sample/targets"})
    before = history.samples()
    for path in (tmp_path / "other", tmp_path / "broken.npz", tmp_path / "incomplete.npz"):
        with pytest.raises(ValueError):
            history.load(path)
        assert history.policy_ids == [0, 1, 2]
        np.testing.assert_array_equal(history.samples()[0], before[0])
        np.testing.assert_array_equal(history.samples()[1], before[1])


def test_a_file_that_is_not_a_history_is_one_clear_error(tmp_path):
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, representation="opr", seed=0)
    _fill(history, 2, 10)
    history.save(tmp_path / "good")
    good = (tmp_path / "good.npz").read_bytes()
    files = {
        "empty.npz": b"",
        "truncated.npz": good[: len(good) // 2],
        "text.npz": b"a history? no, some text\n",
        "object.pkl": b"\x80\x04\x95\x05\x00\x00\x00\x00\x00\x00\x00K\x01.",
    }
    for name, content in files.items():
        (tmp_path / name).write_bytes(content)
    np.savez(tmp_path / "foreign.npz", weights=np.zeros(3))
    np.savez(tmp_path / "bad_meta.npz", meta=np.array("not json"))
    for name in [*files, "foreign.npz", "bad_meta.npz"]:
        with pytest.raises(ValueError) as raised:
            history.load(tmp_path / name)
        message = str(raised.value)
        assert message.startswith(f"{tmp_path / name} is not a policy history file: save_history()"), message
        assert "allow_pickle" not in message and raised.value.__cause__ is None and raised.value.__suppress_context__
        assert history.policy_ids == [0, 1]
    with np.load(tmp_path / "good.npz") as archive:
        np.savez(tmp_path / "incomplete.npz", **{k: archive[k] for k in archive.files if k != "record/params"})
    with pytest.raises(ValueError, match=r"incomplete.npz is incomplete: it has no 'record/params'"):
        history.load(tmp_path / "incomplete.npz")
    with pytest.raises(FileNotFoundError):
        history.load(tmp_path / "missing.npz")


def test_save_is_atomic_and_takes_file_objects(tmp_path, monkeypatch):
    import io

    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    _fill(history, 2, 10)
    buffer = io.BytesIO()
    history.save(buffer)
    buffer.seek(0)
    loaded = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4).load(buffer)
    assert loaded.policy_ids == [0, 1] and loaded.n_samples == 20
    history.save(tmp_path / "h")
    old = (tmp_path / "h.npz").read_bytes()
    _fill(history, 1, 10)

    def failing_savez(*args, **kwargs):
        args[0].write(b"partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError, match="disk full"):
        history.save(tmp_path / "h")
    assert (tmp_path / "h.npz").read_bytes() == old and [p.name for p in tmp_path.iterdir()] == ["h.npz"]


def test_non_finite_values_are_refused_where_they_enter(tmp_path):
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    bad_record = _record(0)
    bad_record["params"][3] = np.nan
    with pytest.raises(ValueError, match=r"non-finite policy record field 'params': nan at index \(3,\)"):
        history.add_record(bad_record)
    assert history.n_policies == 0
    pid = history.add_record(_record(0))
    with pytest.raises(ValueError, match="non-finite value targets: inf"):
        history.add_samples(np.zeros((3, 3)), np.array([0.0, np.inf, 1.0]), pid)
    with pytest.raises(ValueError, match="non-finite observations 'obs'"):
        history.add_samples(np.full((3, 3), -np.inf), np.zeros(3), pid)
    assert history.n_samples == 0
    # a file with a NaN (written by hand: the history never holds one) is refused on load, the history kept
    history.add_samples(np.zeros((3, 3)), np.zeros(3), pid)
    history.save(tmp_path / "h")
    with np.load(tmp_path / "h.npz") as archive:
        arrays = {k: archive[k] for k in archive.files}
    arrays["sample/targets"][1] = np.nan
    np.savez(tmp_path / "nan.npz", **arrays)
    with pytest.raises(ValueError, match="non-finite value targets"):
        history.load(tmp_path / "nan.npz")
    assert history.n_samples == 3


def test_load_checks_every_layer_and_the_spaces(tmp_path):
    from sb3_pevfa.pevfa.records import ActorLayout

    def history_of(layout, obs=OBS):
        return PolicyHistory(obs, ACT, layout.n_params, n_state_action_pairs=4, representation="opr", layout=layout)

    # two actors with the same number of parameters (22) but other layers
    a = ActorLayout(linear_shapes=((4, 2), (2, 4)), log_std_shape=())
    b = ActorLayout(linear_shapes=((2, 2), (2, 2), (2, 4)), log_std_shape=())
    assert a.n_params == b.n_params == 22
    history = history_of(a)
    history.add_record({**_record(0, n_params=22)})
    history.save(tmp_path / "h")
    with pytest.raises(ValueError, match=r"actor_linear_shapes: file has \[\[4, 2\], \[2, 4\]\], model expects \[\[2, 2\]"):
        history_of(b).load(tmp_path / "h")
    bounded = gym.spaces.Box(-2, 2, (3,), np.float32)  # same shape, other bounds
    with pytest.raises(ValueError, match="observation_space: file has"):
        history_of(a, bounded).load(tmp_path / "h")
    history_of(a).load(tmp_path / "h")  # the same layout and spaces load


@pytest.mark.parametrize(
    "representation, objectives, pairs",
    [("opr", (), 0), ("rpr", (), 0), ("random", (), 0), ("spr", (), 200), ("opr", ("aux",), 200), ("spr", ("cl",), 200)],
)
def test_records_hold_pairs_only_where_something_reads_them(representation, objectives, pairs):
    from sb3_pevfa import PPOPeVFA

    model = PPOPeVFA("MlpPolicy", "Pendulum-v1", representation=representation, representation_objectives=objectives,
                     n_steps=64, batch_size=32, n_epochs=1, history_learning_starts=0, seed=0)  # fmt: skip
    assert model.policy.n_state_action_pairs == 200  # what was asked, as saved with the model
    model.learn(128)
    records = model.history.records(model.history.policy_ids)
    assert records["states"].shape == (3, pairs, 3) and records["actions"].shape == (3, pairs, 1)
    assert model.history.signature["n_state_action_pairs"] == pairs
    assert model.policy.behaviour_states.shape == (pairs, 3)


def test_max_nbytes_counts_a_full_history():
    history = PolicyHistory(gym.spaces.Box(0, 255, (8, 8, 3), np.uint8), gym.spaces.Discrete(2), n_params=10,
                            n_state_action_pairs=0, buffer_size=100, max_policies=7)  # fmt: skip
    # a sample: 192 uint8 + float32 target + int64 id; a record: 10 float32 parameters
    assert history.max_nbytes == 100 * (192 + 4 + 8) + 7 * 40
    for _ in range(10):
        history.add_record({"params": np.zeros(10, np.float32), "states": np.zeros((0, 192), np.float32),
                            "actions": np.zeros((0, 1), np.float32), "codes": np.zeros(0, np.float32)})  # fmt: skip
        history.add_samples(np.zeros((30, 8, 8, 3), np.uint8), np.zeros(30), history.latest_policy_id)
    assert history.nbytes == history.max_nbytes


def test_a_history_that_can_grow_past_gigabytes_is_announced():
    from stable_baselines3.common.envs import FakeImageEnv

    from sb3_pevfa import PPOPeVFA

    env = FakeImageEnv(screen_height=84, screen_width=84, n_channels=4, discrete=True)
    with pytest.warns(UserWarning, match=r"can grow to 5\.4 GiB \(history_buffer_size=200000"):
        PPOPeVFA("CnnPolicy", env, n_steps=64, batch_size=32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        PPOPeVFA("CnnPolicy", env, n_steps=64, batch_size=32, history_buffer_size=20_000)
        PPOPeVFA("MlpPolicy", "Pendulum-v1", representation="spr")


def test_grouped_batches_read_few_policies_and_keep_the_uniform_distribution():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    for i, n in enumerate([100, 300, 600, 50]):  # unequal sample counts; policy 3 is the current one
        pid = history.add_record(_record(i))
        history.add_samples(np.full((n, 3), i, np.float32), np.arange(n, dtype=np.float32) + 1000 * i, pid)
    batches = [history.sample_grouped(64, 4, exclude_policy=3) for _ in range(3000)]
    for observations, targets, ids in batches[:50]:
        assert len(ids) == 64 and len(np.unique(ids)) <= 4 and 3 not in ids
        # 16 samples per drawn policy (a policy drawn twice has 32), each with its own policy's row
        assert all(len(np.unique(ids[i : i + 16])) == 1 for i in range(0, 64, 16))
        np.testing.assert_array_equal(observations[:, 0], ids)
        np.testing.assert_array_equal(targets // 1000, ids)
    ids = np.concatenate([b[2] for b in batches])
    # every eligible sample is equally likely: policies in proportion to their counts (100:300:600) ...
    np.testing.assert_allclose(np.bincount(ids, minlength=3)[:3] / len(ids), [0.1, 0.3, 0.6], atol=0.02)
    # ... and the samples of a policy uniform among its own
    within = np.concatenate([b[1][b[2] == 2] for b in batches]) - 2000
    assert within.min() == 0 and within.max() == 599
    np.testing.assert_allclose(np.histogram(within, bins=6, range=(0, 600))[0] / len(within), 1 / 6, atol=0.01)
    # the remainder goes to the first policies (3, 3, 2, 2 of 10); more policies than samples: one sample each
    ids = history.sample_grouped(10, 4)[2]
    assert len(ids) == 10 and all(len(np.unique(ids[a:b])) == 1 for a, b in ((0, 3), (3, 6), (6, 8), (8, 10)))
    assert history.sample_grouped(4, 8)[2].shape == (4,)


def test_grouped_sampling_is_seeded_and_none_without_eligible_samples():
    def draw(seed):
        history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=seed)
        _fill(history, 5, 40)
        return [history.sample_grouped(32, 2, exclude_policy=4)[2] for _ in range(10)]

    assert all(np.array_equal(a, b) for a, b in zip(draw(0), draw(0)))
    assert not all(np.array_equal(a, b) for a, b in zip(draw(0), draw(1)))
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    _fill(history, 1, 10)
    assert history.sample_grouped(8, 2, exclude_policy=0) is None
    history.add_record(_record(1))  # a policy without samples yet is never drawn
    assert set(history.sample_grouped(64, 8)[2].tolist()) == {0}


def test_grouped_sampling_after_evictions_a_sampleless_record_and_a_reload(tmp_path):
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, buffer_size=250, max_policies=4, seed=0)
    for i, n in enumerate([100, 100, 0, 100, 80]):  # policy 2 gets no samples; the ring wraps, then 0 is evicted
        pid = history.add_record(_record(i))
        if n:
            history.add_samples(np.full((n, 3), i, np.float32), np.full(n, float(i)), pid)
    assert history.policy_ids == [1, 2, 3, 4] and [history.sample_count(p) for p in (1, 2, 3, 4)] == [70, 0, 100, 80]
    batches = [history.sample_grouped(20, 2, exclude_policy=4) for _ in range(2000)]
    ids = np.concatenate([b[2] for b in batches])
    np.testing.assert_allclose([np.mean(ids == 1), np.mean(ids == 3)], [70 / 170, 100 / 170], atol=0.02)
    for observations, targets, policy_ids in batches:
        np.testing.assert_array_equal(observations[:, 0], policy_ids)
        np.testing.assert_array_equal(targets, policy_ids)
    # a reloaded history draws the same batches (records, counts and the sampling RNG's state travel)
    history.save(tmp_path / "h")
    loaded = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, buffer_size=250, max_policies=4).load(tmp_path / "h")
    for _ in range(5):
        for got, want in zip(loaded.sample_grouped(16, 4, exclude_policy=4), history.sample_grouped(16, 4, exclude_policy=4)):
            np.testing.assert_array_equal(got, want)


def test_one_add_larger_than_the_buffer_keeps_its_newest_samples_and_every_sample_can_be_drawn():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, buffer_size=10, seed=0)
    pid = history.add_record(_record(0))
    history.add_samples(np.zeros((15, 3), np.float32), np.arange(15, dtype=np.float32), pid)
    assert history.n_samples == history.sample_count(pid) == 10
    np.testing.assert_array_equal(history.samples()[1], np.arange(5, 15))
    drawn = np.concatenate([history.sample(32)[1] for _ in range(50)])  # uniform: the oldest and newest included
    assert set(drawn.tolist()) == set(range(5, 15))
    single = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    _fill(single, 1, 1)
    assert single.sample(4)[1].tolist() == [0.0] * 4


def test_grouped_draws_are_uniform_over_policies_of_one_sample_and_see_a_new_record():
    history = PolicyHistory(OBS, ACT, 5, n_state_action_pairs=4, seed=0)
    _fill(history, 3, 1)
    ids = np.concatenate([history.sample_grouped(3, 3)[2] for _ in range(3000)])
    np.testing.assert_allclose(np.bincount(ids, minlength=3) / len(ids), [1 / 3] * 3, atol=0.03)
    # a record added after draws: the latest policy is now 3, without samples, so policy 2's samples are eligible
    history.add_record(_record(3))
    drawn = np.concatenate([history.sample_grouped(8, 2, exclude_policy=3)[2] for _ in range(20)])
    assert set(drawn.tolist()) == {0, 1, 2}


@pytest.mark.parametrize(
    ("field", "other"),
    [
        ("action_space_details", dict(action_space=gym.spaces.Box(-2, 2, (1,), np.float32))),  # other bounds
        ("code_dim", dict(code_dim=3)),
        ("n_state_action_pairs", dict(n_state_action_pairs=8)),
        ("representation", dict(representation="opr")),
        ("n_params", dict(n_params=6)),
    ],
)
def test_load_names_the_field_that_differs(tmp_path, field, other):
    kwargs = dict(observation_space=OBS, action_space=gym.spaces.Box(-1, 1, (1,), np.float32), n_params=5,
                  n_state_action_pairs=4, code_dim=2, representation="random")  # fmt: skip
    saved = PolicyHistory(**kwargs)
    saved.add_record(_record(0, code_dim=2))
    saved.save(tmp_path / "h")
    with pytest.raises(ValueError, match=f"{field}: file has"):
        PolicyHistory(**{**kwargs, **other}).load(tmp_path / "h")
    PolicyHistory(**kwargs).load(tmp_path / "h")  # the same settings load
