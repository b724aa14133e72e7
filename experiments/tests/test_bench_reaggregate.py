"""benchmarks/reaggregate.py: the vote and greedy + vote combinations of sampled answers (predict's `aggregation: votes`
and `greedy_votes`, which the script now calls), on the answers and hand-computed plans the script was first checked
with."""

from benchmark_support import load_benchmark

from degusta_learn.prompting.aggregate import aggregate_votes
from degusta_learn.prompting.answers import AnswerItem
from degusta_learn.render.grid import Grid
from degusta_learn.scene import Placement


def item(oid: int, cell: str) -> AnswerItem:
    return AnswerItem(type="cup", id=oid, cells=[cell], direction="N")


ANSWERS = [[item(1, "A1"), item(2, "B2"), item(3, "C3")],
           [item(2, "B2"), item(1, "A3"), item(4, "D4"), item(5, "E5")],
           [item(1, "A1"), item(4, "D4"), item(2, "B2"), item(6, "F6")]]


def test_votes_take_the_median_length_of_the_most_named_objects_in_their_mean_order():
    plan = aggregate_votes(ANSWERS, "grid", Grid(8, 8))[0]
    # the median length is 4: 1 and 2 (3 votes), 4 (2), then 3 (1 vote, at step 2: before 5 and 6, at step 3);
    # in the order of their mean steps (0.33, 1.0, 1.5, 2)
    assert [p.object for p in plan] == [1, 2, 4, 3]
    one = Grid(8, 8).decode_weighted([["A1"], ["A3"], ["A1"]])
    assert (plan[0].x, plan[0].y) == (float(one[0]), float(one[1]))  # the mean of its cells over the answers
    assert aggregate_votes([], "grid", Grid(8, 8))[0] == []


def test_greedy_plus_votes_keeps_the_greedy_answer_and_only_lengthens_it():
    """The script's greedy + votes is predict's `greedy_votes` (`anchored_votes`), on the script's first checks."""
    from degusta_learn.prompting.aggregate import anchored_votes

    bench = load_benchmark("reaggregate")
    greedy = [item(9, "D4")]
    plan = anchored_votes(greedy, ANSWERS, "grid", Grid(8, 8))[0]
    assert plan[0] == Placement(object=9, x=0.4375, y=0.4375, rotation=0.0)  # D4's centre, as the greedy answer put it
    assert [p.object for p in plan[1:]] == [1, 2, 4]  # up to the median length, 4
    long = [item(k, "A1") for k in range(10, 16)]
    assert [p.object for p in anchored_votes(long, ANSWERS, "grid", Grid(8, 8))[0]] == list(range(10, 16))  # never shortened
    assert anchored_votes(greedy, [], "grid", Grid(8, 8))[0] == plan[:1]
    assert bench.median_length(ANSWERS) == 4 and bench.median_length([[], []]) == 1  # fixed_length's (at least 1)
