"""`prompt_style: paper` (issue 53, item 1): the paper's appendix prompts verbatim beside the `clarified` default.

The appendix text is read from the paper itself (../shared/paper/000_*.txt beside the repository), so a change of
either the paper file or the package's copy fails here; the `clarified` text is pinned by hand-copied lines.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
import yaml
from conftest import make_small_dataset

from degusta_learn.errors import DegustaError
from degusta_learn.methods import build_config, get_method, run_predict
from degusta_learn.prompting.cache import prompt_digest
from degusta_learn.prompting.costs import prompt_tokens
from degusta_learn.render.grid import Grid
from degusta_learn.render.lifting import Renderer, oal_text
from degusta_learn.scene import load_dataset, make_episodes, read_predictions, save_dataset
from degusta_learn.task.answers import read_answer
from degusta_learn.task.prompt import PAPER_PROMPTS, build_prompt
from degusta_learn.vlm.prompt_options import PromptOptions, adapt_prompt

PAPER_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "paper"
DS = make_small_dataset(n_participants=3, n_trials=5)
R = Renderer.for_dataset(DS, size=64)
G = Grid(8, 8)
QUESTION = "What objects should I place in this image"


def appendix_blocks() -> dict[str, str]:
    """{bold title: raw spverbatim body} of the appendix's "Prompts" subsection (skips without the paper)."""
    files = sorted(PAPER_DIR.glob("000_*.txt")) if PAPER_DIR.is_dir() else []
    if not files:
        pytest.skip(f"the paper's LaTeX is not at {PAPER_DIR} (a checkout without ../shared/paper)")
    tex = files[0].read_text(encoding="utf-8")
    section = tex[tex.index("\\subsection{Prompts}"):]
    section = section[:section.index("\\section{")]
    blocks = re.findall(r"\\textbf\{([^}]*)\}\s*\\begin\{spverbatim\}(.*?)\\end\{spverbatim\}", section, re.S)
    return {title.strip(): body for title, body in blocks}


def as_text(body: str) -> str:
    """LaTeX -> text: the spverbatim body with its whitespace runs made one space and its quote marks (`, ‘, ’)
    written as '."""
    return re.sub(r"\s+", " ", body).strip().translate(str.maketrans("`‘’", "'''"))


@pytest.fixture(scope="module")
def appendix():
    found = {title: as_text(body) for title, body in appendix_blocks().items()}
    assert set(found) == {"Objects as Language", "Unmarked Arrangements", "Grid Marked Arrangements"}
    return found


def task(method: str, k: int, **kw) -> str:
    return build_prompt(method, DS, make_episodes(DS, k, "all")[0], R, G, style="paper", **kw).parts[-1]


# ----------------------------------------------------------------------------- the verbatim text


def test_the_package_copy_is_the_appendix(appendix):
    expected = {"objects_as_language": appendix["Objects as Language"], "unmarked": appendix["Unmarked Arrangements"],
                "grid": appendix["Grid Marked Arrangements"]}
    assert expected == PAPER_PROMPTS
    # the normalisation did something real: the appendix writes backticks and typographic quotes
    raw = appendix_blocks()
    assert "`type'" in raw["Grid Marked Arrangements"] and "‘rotation’" in raw["Objects as Language"]
    assert "[{'type':object_type, 'id': object_reference_id, 'position': [x, y], 'rotation': degrees}]" \
        in appendix["Objects as Language"]


@pytest.mark.parametrize("k", [2, 4])
def test_each_method_sends_its_appendix_prompt(appendix, k):
    names = ", ".join(f"final_state_{i}.jpg" for i in range(1, k + 1))
    oal, unmarked, grid = (appendix[t] for t in ("Objects as Language", "Unmarked Arrangements",
                                                  "Grid Marked Arrangements"))
    assert task("louma", k) == oal  # no placeholder in the objects-as-language prompt
    assert task("mouma", k) == unmarked.replace("final_state_K.jpg", names)
    assert task("mogma", k) == grid.replace("final_state_N.jpg", names)
    # logma: the objects-as-language prompt to its question, then the grid prompt's answer sentences
    assert task("logma", k) == oal[:oal.index(QUESTION)] + grid[grid.index(QUESTION):]
    assert task("logma", k).endswith(grid[grid.index("Please list all grid cells"):])


def test_placeholders_without_context_and_png_names(appendix):
    assert task("mogma", 0) == appendix["Grid Marked Arrangements"]  # nothing to fill: the appendix as written
    assert task("mouma", 0) == appendix["Unmarked Arrangements"]
    png = task("mouma", 2, image_format="png")
    names = "final_state_1.png, final_state_2.png"
    assert png == appendix["Unmarked Arrangements"].replace("final_state_K.jpg", names).replace("initial_state_1.jpg",
                                                                                               "initial_state_1.png")


def test_structured_outputs_change_only_the_answer_format_sentences(appendix):
    grid = appendix["Grid Marked Arrangements"].replace("final_state_N.jpg", "final_state_1.jpg, final_state_2.jpg")
    expected = grid.replace(
        "Give your answer as a python list formatted as follows: [{'type':object_type, 'id': object_reference_id, "
        "'position':[grid_cell_ids], 'cardinal_direction':direction}].",
        'Give your answer as a JSON object formatted as follows: {"objects": [{"type":object_type, "id": '
        'object_reference_id, "position":[grid_cell_ids], "cardinal_direction":direction}]}.').replace(
        "Include only this list in your response.", "Include only this JSON object in your response.")
    assert expected != grid and task("mogma", 2, structured=True) == expected
    assert "python list" not in task("louma", 2, structured=True)


def test_paper_parts_have_no_preamble_and_keep_images_labels_and_order_lines():
    ep = make_episodes(DS, 2, "all")[0]
    for method in ("louma", "logma", "mouma", "mogma"):
        paper = build_prompt(method, DS, ep, R, G, style="paper")
        clarified = build_prompt(method, DS, ep, R, G)
        assert paper.style == "paper" and clarified.style == "clarified"
        assert [(p.name, p.image.tobytes()) for p in paper.images] == \
            [(p.name, p.image.tobytes()) for p in clarified.images]
        assert "These are the objects I have" not in paper.text
        labels = [p for p in paper.parts if isinstance(p, str) and p.endswith(":") and "\n" not in p]
        assert labels == [f"{p.name}:" for p in paper.images]
        assert sum(p.startswith("Placement order in final_state_") for p in paper.parts if isinstance(p, str)) == 2
    assert build_prompt("louma", DS, ep, R, G, style="paper").parts[0] == oal_text(DS.catalog)  # the JSON alone
    assert build_prompt("mogma", DS, ep, R, G, style="paper").parts[0] == "objects_cup.jpg:"


def test_adapting_keeps_the_style_and_drops_dropped_sheets_labels():
    paper = build_prompt("mogma", DS, make_episodes(DS, 2, "all")[0], R, G, style="paper")
    small = adapt_prompt(paper, PromptOptions(include=["context", "target"]))
    assert small.style == "paper" and not any(p.startswith("objects") for p in small.parts if isinstance(p, str))
    assert [p.name for p in small.images] == ["final_state_1.jpg", "final_state_2.jpg", "initial_state_1.jpg"]
    assert adapt_prompt(paper, PromptOptions(compose=["objects"])).style == "paper"


def test_an_unknown_style_is_one_line():
    with pytest.raises(DegustaError, match=r"style: expected one of \['clarified', 'paper'\], got 'verbatim'"):
        build_prompt("mogma", DS, make_episodes(DS, 2, "all")[0], R, G, style="verbatim")


# ----------------------------------------------------------------------------- clarified is unchanged


def test_clarified_is_unchanged():
    ep = make_episodes(DS, 2, "all")[0]
    mogma = build_prompt("mogma", DS, ep, R, G)
    assert mogma.parts[0] == ("These are the objects I have, one image per object type. Each object is marked with "
                              "its object_reference_id.")
    assert mogma.parts[-1] == (
        "My preferences for setting a table are shown in the images named final_state_1.jpg and final_state_2.jpg. "
        "You are helping me set the table in initial_state_1.jpg according to my preferences. What objects should I "
        "place in this image, where should I place them, and how should they be oriented? The grid over "
        "initial_state_1.jpg names columns A to H from the left and rows 1 to 8 from the top; a grid cell id is the "
        "column letter followed by the row number, e.g. C7. Please list all grid cells the object will intersect "
        "after it is placed. Give the orientation as the closest cardinal direction [N, NE, E, SE, S, SW, W, NW] the "
        "object is pointing in after it is placed. The top of the image is N. Give your answer as a python list "
        "formatted as follows: [{'type': object_type, 'id': object_reference_id, 'position': [grid_cell_ids], "
        "'cardinal_direction': direction}]. Give grid_cell_ids as a list of string. object_type is one of cup, fork, "
        "knife, plate, spoon. Give object_id as an integer. List the objects in the order I should place them. "
        "Include only this list in your response.")
    louma = build_prompt("louma", DS, make_episodes(DS, 0, "all")[0], R, G)
    assert louma.parts[0].startswith("These are the objects I have, as JSON; each object's object_reference_id is "
                                     "its \"id\" and its object_type is its \"class\":\n[\n{")
    assert louma.parts[-1].startswith(
        "You are helping me set the table in initial_state_1.jpg the way I would like it. You have not seen any of "
        "my previous table settings. What objects should I place in this image")
    assert "(x from the left edge, y from the top edge of the image)" in louma.parts[-1]
    assert build_prompt("mogma", DS, ep, R, G, style="clarified").parts == mogma.parts


# ----------------------------------------------------------------------------- what the parser reads


@pytest.mark.parametrize("text,kind", [
    ("[{`type':'plate', `id': 75, `position':['D4', 'E4'], `cardinal_direction':'NE'}]", "grid"),
    ("[{'type':'plate', 'id': 75, 'position':[\"D4\"], 'cardinal_direction':'N'}]", "grid"),
    ("[{‘type’:'plate', 'id': 75, 'position': [0.5, 0.25], ‘rotation’: 90}]", "unmarked"),
])
def test_the_format_the_paper_asks_for_parses(text, kind):
    items = read_answer(text, kind, DS.catalog, G).items
    assert [(i.type, i.id) for i in items] == [("plate", 75)]
    if kind == "grid":
        assert items[0].cells[0] == "D4" and items[0].direction in ("N", "NE")
    else:
        assert items[0].position == (0.5, 0.25) and items[0].rotation == 90.0


# ----------------------------------------------------------------------------- configs, runs and the dry run


@pytest.fixture
def data(tmp_path):
    return save_dataset(make_small_dataset(n_participants=3, n_trials=3), tmp_path / "data")


def zeroshot_config(tmp_path, data, backend: dict, **extra) -> str:
    cfg = {"method": "mogma", "dataset": str(data), "out": str(tmp_path / "run" / "predictions.jsonl"),
           "context": 2, "split": "all", "render_size": 64, "concurrency": 1, "backend": backend,
           "decoding": {"n": 1, "temperature": 0.0}, **extra}
    path = tmp_path / "zeroshot.yaml"
    path.write_text("# degusta predict --config zeroshot.yaml\n" + yaml.safe_dump(cfg))
    return str(path)


def test_a_run_records_its_style_in_every_prediction_and_the_ledger(tmp_path, data):
    ds = load_dataset(data)
    answers = tmp_path / "answers.jsonl"
    answers.write_text("".join(json.dumps({"episode": ep.id, "sample": 0, "text": "[{'type': 'plate', 'id': 75, "
                                           "'position': ['D4'], 'cardinal_direction': 'N'}]"}) + "\n"
                               for ep in make_episodes(ds, 2, "all")))
    out = run_predict(zeroshot_config(tmp_path, data, {"name": "replay", "path": str(answers)}, prompt_style="paper"))
    preds = read_predictions(out, ds.catalog)
    assert len(preds) == 9 and {p.diagnostics["prompt_style"] for p in preds} == {"paper"}
    assert json.loads((tmp_path / "run" / "ledger.json").read_text())["prompt_style"] == "paper"


def test_the_style_reaches_the_prompt_and_keys_its_own_cache_entries(tmp_path, data):
    from degusta_learn.prompting.runner import ZeroShotRun

    ds = load_dataset(data)
    ep = make_episodes(ds, 2, "all")[0]
    runs = {}
    for style in ("clarified", "paper"):
        _, cfg = build_config(zeroshot_config(tmp_path, data, {"name": "openai", "base_url": "http://127.0.0.1:9/v1"},
                                              prompt_style=style), [], "method", get_method)
        runs[style] = ZeroShotRun(cfg, ds).prompt(ep)
    (clar, clar_keys), (paper, paper_keys) = runs["clarified"], runs["paper"]
    assert clar.style == "clarified" and paper.style == "paper"
    assert paper.parts[-1].startswith("My preferences for setting a table are shown in the images named "
                                      "final_state_1.jpg, final_state_2.jpg. You are helping")
    assert prompt_digest(clar) != prompt_digest(paper) and set(clar_keys).isdisjoint(paper_keys)
    # the clarified default keys what it keyed before the option existed: the config without the key
    _, default = build_config(zeroshot_config(tmp_path, data, {"name": "openai", "base_url": "http://127.0.0.1:9/v1"}),
                              [], "method", get_method)
    assert default.prompt_style == "clarified" and ZeroShotRun(default, ds).prompt(ep)[1] == clar_keys


def test_a_config_with_an_unknown_style_is_one_line(tmp_path, data):
    path = zeroshot_config(tmp_path, data, {"name": "openai", "base_url": "http://127.0.0.1:9/v1"},
                           prompt_style="verbatim")
    with pytest.raises(DegustaError, match="prompt_style") as e:
        build_config(path, [], "method", get_method)
    assert "\n" not in str(e.value)


def test_the_dry_run_shows_the_input_tokens_of_both_styles(tmp_path, data, capsys):
    path = zeroshot_config(tmp_path, data, {"name": "openai", "base_url": "http://127.0.0.1:9/v1"},
                           prompt_style="paper", context=None,
                           episodes=str(mixed_episodes(tmp_path, data)))
    assert run_predict(path, dry_run=True) is None
    line = next(x for x in capsys.readouterr().out.splitlines() if "prompt_style:" in x)
    # expected: every episode's prompt built in both styles and counted with the estimator (no shortcut)
    ds = load_dataset(data)
    from degusta_learn.scene import read_episodes

    episodes = read_episodes(tmp_path / "episodes.jsonl", ds)
    renderer = Renderer.for_dataset(ds, size=64)
    mean = {s: round(sum(prompt_tokens(build_prompt("mogma", ds, ep, renderer, G, style=s)) for ep in episodes)
                     / len(episodes)) for s in ("clarified", "paper")}
    assert mean["clarified"] > mean["paper"]  # the clarified additions cost tokens
    assert line.strip() == (f"prompt_style: paper (input tokens a request by prompt style: clarified "
                            f"{mean['clarified']:,}, paper {mean['paper']:,})")


def mixed_episodes(tmp_path, data) -> Path:
    """An episodes file of context lengths 0 and 2 (the style difference depends on the context length)."""
    from degusta_learn.scene.episodes import write_episodes

    ds = load_dataset(data)
    episodes = make_episodes(ds, 0, "all")[:2] + make_episodes(ds, 2, "all")[:3]
    path = tmp_path / "episodes.jsonl"
    write_episodes(path, episodes)
    return path
