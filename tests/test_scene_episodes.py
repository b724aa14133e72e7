import pytest

from degusta_learn.errors import DegustaError
from degusta_learn.scene import make_episodes, read_episodes, split_participants, write_episodes


def test_splits_are_disjoint_cover_everyone_and_are_deterministic():
    ids = [f"p{i:03d}" for i in range(199)]
    s = split_participants(ids, seed=0)
    assert set(s["train"]) | set(s["val"]) | set(s["test"]) == set(ids)
    assert not set(s["train"]) & set(s["test"]) and not set(s["train"]) & set(s["val"]) and not set(s["val"]) & set(s["test"])
    assert (len(s["train"]), len(s["val"]), len(s["test"])) == (139, 20, 40)
    assert split_participants(list(reversed(ids)), seed=0) == s
    assert split_participants(ids, seed=1) != s


def test_episode_participants_never_leak_across_splits(small_dataset):
    train = {e.participant for e in make_episodes(small_dataset, 4, "train")}
    test = {e.participant for e in make_episodes(small_dataset, 4, "test")}
    assert train and test and not train & test


@pytest.mark.parametrize("k", [0, 2, 4])
def test_episodes_per_context_length(small_dataset, k):
    eps = make_episodes(small_dataset, k, "all")
    assert len(eps) == 10 * 5
    for e in eps:
        assert len(e.context) == k and e.target not in e.context and e.id.endswith(f"/k{k}")
        tables = {small_dataset.arrangement(e.participant, t).table for t in e.context}
        target_table = small_dataset.arrangement(e.participant, e.target).table
        assert e.task == ("reconstruction" if target_table in tables else "generalization")
    assert make_episodes(small_dataset, k, "all") == eps


def test_episodes_file_round_trip_and_errors(small_dataset, tmp_path):
    eps = make_episodes(small_dataset, 2, "all")
    write_episodes(tmp_path / "e.jsonl", eps)
    assert read_episodes(tmp_path / "e.jsonl", small_dataset) == eps
    (tmp_path / "bad.jsonl").write_text('{"id": "x", "participant": "p000", "context": [1], "target": 9}\n')
    with pytest.raises(DegustaError, match=r"bad.jsonl:1: field 'target': participant 'p000' has no trial 9"):
        read_episodes(tmp_path / "bad.jsonl", small_dataset)
    with pytest.raises(DegustaError, match="at least 3 participants"):
        split_participants(["a", "b"])


def test_an_episode_whose_context_contradicts_its_k_id_names_the_line(tmp_path, small_dataset):
    """A k4 episode edited to two context trials was run as it was (the id still said k4)."""
    import json

    path = tmp_path / "e.jsonl"
    write_episodes(path, make_episodes(small_dataset, 4, "all"))
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    rows[1]["context"] = rows[1]["context"][:2]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    with pytest.raises(DegustaError, match=r"e.jsonl:2: .*context.*2 trials, but the id .* says context length 4"):
        read_episodes(path, small_dataset)
