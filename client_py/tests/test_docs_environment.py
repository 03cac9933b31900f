"""docs/environment.md states what the code does: its tables of options, constants, spaces,
observation bounds, outcome codes, spawn rows and rendering are compared with the code (the
C++ headers that define them, the proto, and a running server), and its labelled frame with
what the renderer draws now.

The labelled frame, docs/environment_frame.png, is made by this file:

    MLL_SERVER_BIN=build/server/service/mll_server \\
        .venv/bin/python client_py/tests/test_docs_environment.py --write-frame

test_labelled_frame_is_what_the_renderer_draws fails when the renderer has changed since.
"""

from __future__ import annotations

import math
import pathlib
import re
import sys

import grpc
import numpy as np
import pytest

import multi_lunar_lander as mll

_REPO = pathlib.Path(__file__).resolve().parents[2]
_DOC = _REPO / "docs" / "environment.md"
_FRAME_PNG = _REPO / "docs" / "environment_frame.png"
_CONFIG_H = _REPO / "proto" / "include" / "mll" / "env_spec.h"
_CONSTANTS_H = _REPO / "server" / "core" / "src" / "constants.h"
_RENDERER_H = _REPO / "server" / "core" / "include" / "mll" / "core" / "renderer.h"


# --- Reading the document and the headers. ---


def _section(title: str) -> str:
    """The text of the section whose heading is `title` (any level), up to the next heading of
    the same or a higher level."""
    text = _DOC.read_text(encoding="utf-8")
    match = re.search(rf"^(#+) {re.escape(title)}[ \t]*$", text, re.MULTILINE)
    assert match, f"docs/environment.md has no section '{title}'"
    level = len(match.group(1))
    rest = text[match.end():]
    end = re.search(rf"^#{{1,{level}}} ", rest, re.MULTILINE)
    return rest[: end.start()] if end else rest


def _flat(text: str) -> str:
    """`text` with every run of white space (line breaks included) as one space."""
    return " ".join(text.split())


def _table(section: str, first_header: str) -> list[list[str]]:
    """The rows (cells stripped of spaces and backquotes) of the table in `section` whose first
    header cell is `first_header`."""
    lines = section.split("\n")
    for index, line in enumerate(lines):
        cells = _cells(line)
        if cells and cells[0] == first_header:
            rows = []
            for row in lines[index + 2:]:
                if not row.startswith("|"):
                    break
                rows.append(_cells(row))
            return rows
    raise AssertionError(f"no table starting with '{first_header}'")


def _cells(line: str) -> list[str]:
    if not line.startswith("|"):
        return []
    return [cell.strip().replace("`", "") for cell in re.split(r"(?<!\\)\|", line.strip())[1:-1]]


def _options_in_code() -> dict[str, tuple[str, str, str]]:
    """name -> (C++ type, default, range as OptionRange::Describe() words) from MLL_ENV_OPTIONS."""
    text = _CONFIG_H.read_text()
    body = text[text.index("#define MLL_ENV_OPTIONS(X)"):]
    body = body[: body.index("\n\n")].replace("\\\n", " ")
    found = {}
    for kind, name, default, range_call in re.findall(
        r"X\((\w+),\s*(\w+),\s*([^,]+),\s*::mll::OptionRange::(\w+\([^)]*\)?\)?)", body
    ):
        found[name] = (kind, default.strip(), _describe(range_call))
    return found


def _describe(range_call: str) -> str:
    """OptionRange::Describe() of a range written in env_spec.h."""
    constants = {"::mll::kMinLanders": "1", "::mll::kMaxLanders": "32"}
    for name, value in constants.items():
        range_call = range_call.replace(name, value)
    kind, _, args = range_call.partition("(")
    values = [_number(a) for a in re.split(r",\s*", args.rstrip(")").strip()) if a]
    return {
        "Any": lambda: "",
        "Integers": lambda: f"{values[0]}..{values[1]}",
        "AtLeast": lambda: f">= {values[0]}",
        "Closed": lambda: f"[{values[0]}, {values[1]}]",
        "Open": lambda: f"({values[0]}, {values[1]}), exclusive",
        "Finite": lambda: "any finite value",
    }[kind]()


def _number(text: str) -> str:
    value = float(text.rstrip("f"))
    return str(int(value)) if value == int(value) else repr(value)


def _cpp_constants(path: pathlib.Path) -> dict[str, float]:
    """name -> value of every `inline constexpr double/int kName = <expression>;` of `path`,
    expressions evaluated in order (they may use the constants above them)."""
    values: dict[str, float] = {}
    for name, expression in re.findall(
        r"inline constexpr (?:double|int) (k\w+) =\s*([^;]+);", path.read_text()
    ):
        values[name] = eval(expression.replace("\n", " "), {}, dict(values))  # noqa: S307 (our header)
    return values


# --- The summary table, spaces and the environment's name. ---


@pytest.fixture(scope="module")
def env(address):
    environment = mll.parallel_env(address=address)
    yield environment
    environment.close()


def test_summary_table_is_the_environments(env, address):
    rows = {row[0]: row[1] for row in _table(_DOC.read_text(), "")}
    assert env.metadata["name"] in rows["Environment id"]
    assert str(env.action_space("lander_0")) in rows["Action space"]
    continuous = mll.parallel_env(address=address, continuous=True)
    try:
        assert str(continuous.action_space("lander_0")) in rows["Action space"]
    finally:
        continuous.close()
    assert str(env.observation_space("lander_0")) in rows["Observation space"]
    assert f"1/{env.metadata['render_fps']} s" in rows["Step"]
    assert rows["Render modes"].startswith("None, " + ", ".join(f'"{m}"' for m in ("rgb_array", "human")))
    assert set(env.metadata["render_modes"]) == {"rgb_array", "human"}


def test_version_history_names_the_current_version(env):
    history = _section("Version history")
    assert f"`{env.metadata['name']}`" in history


# --- Options. ---


def test_options_table_is_the_code():
    """Defaults and ranges as MLL_ENV_OPTIONS defines them, every option once, in its order."""
    rows = _table(_section("Arguments"), "option")
    code = _options_in_code()
    documented = [row[0] for row in rows if row[0] != "render_mode"]
    assert documented == list(code) == list(mll.CONFIG_OPTIONS)
    for name, default, allowed, _ in (row for row in rows if row[0] != "render_mode"):
        kind, code_default, code_range = code[name]
        if kind == "bool":
            assert default == {"true": "True", "false": "False"}[code_default], name
        else:
            assert float(default) == float(code_default), f"{name}: documented {default}, code {code_default}"
        assert allowed == code_range, f"{name}: documented range '{allowed}', code '{code_range}'"


def test_server_defaults_are_the_documented_ones(env):
    rows = {row[0]: row[1] for row in _table(_section("Arguments"), "option")}
    for name, value in env.config.items():
        documented = rows[name]
        if isinstance(value, bool):
            assert documented == str(value), name
        else:
            assert float(documented) == pytest.approx(value), name


def _inside_and_outside(allowed: str) -> tuple[list, list]:
    """Values the documented range allows (its ends) and refuses (just beyond them)."""
    if match := re.fullmatch(r"(-?\d+)\.\.(-?\d+)", allowed):
        low, high = map(int, match.groups())
        return [low, high], [low - 1, high + 1]
    if match := re.fullmatch(r">= (-?\d+)", allowed):
        low = int(match.group(1))
        return [low], [low - 1]
    if match := re.fullmatch(r"\[(\S+), (\S+)\]", allowed):
        low, high = map(float, match.groups())
        return [low, high], [math.nextafter(low, -math.inf), math.nextafter(high, math.inf), math.nan]
    if match := re.fullmatch(r"\((\S+), (\S+)\), exclusive", allowed):
        low, high = map(float, match.groups())
        return [math.nextafter(low, math.inf), math.nextafter(high, -math.inf)], [low, high, math.inf]
    if allowed == "any finite value":
        return [-1e300, 1e300], [math.inf, -math.inf, math.nan]
    assert allowed == "", allowed
    return [False, True], []


def test_server_takes_exactly_the_documented_ranges(address):
    for name, _, allowed, _ in _table(_section("Arguments"), "option"):
        if name == "render_mode":
            continue
        inside, outside = _inside_and_outside(allowed)
        for value in inside:
            mll.parallel_env(address=address, **{name: value}).close()
        for value in outside:
            with pytest.raises(mll.MLLError) as error:
                mll.parallel_env(address=address, **{name: value}).close()
            assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT, (name, value)
            assert name in error.value.message


def test_render_modes_row():
    rows = {row[0]: row for row in _table(_section("Arguments"), "option")}
    assert rows["render_mode"][1] == "None"
    assert rows["render_mode"][2] == 'None, "rgb_array", "human"'


# --- Constants. ---


def test_constants_table_is_the_code():
    code = _cpp_constants(_CONSTANTS_H)
    rows = _table(_section("Constants"), "constant")
    assert rows, "the Constants table is empty"
    for name, value, *_ in rows:
        assert name in code, f"{name} is not a constant of server/core/src/constants.h"
        documented = float(value.split()[0].replace("−", "-"))
        assert documented == pytest.approx(code[name], abs=5e-4), f"{name}: documented {value}, code {code[name]}"


def test_engine_impulses_follow_from_the_constants():
    code = _cpp_constants(_CONSTANTS_H)
    engines = _flat(_section("Engines"))
    main = code["kMainEnginePower"] * code["kMainEngineYLocation"] / code["kScale"]
    side = code["kSideEnginePower"] * code["kSideEngineAway"] / code["kScale"]
    assert f"{main:.2f} x p N s" in engines, main
    assert f"{side:.2f} x p N s" in engines, side
    # Extremes of the dispersion: d0, d1 in [-1/30, 1/30] m.
    d = 1 / code["kScale"]
    low = code["kMainEnginePower"] * (code["kMainEngineYLocation"] / code["kScale"] - 2 * d)
    high = code["kMainEnginePower"] * math.hypot(code["kMainEngineYLocation"] / code["kScale"] + 2 * d, d)
    assert f"{low:.2f} x p to {high:.2f} x p" in engines, (low, high)


# --- Observation. ---


def _observation_bounds() -> dict[int, tuple[float, float]]:
    """index -> (low, high) from the Observation table's bounds column."""
    bounds = {}
    for row in _table(_section("Observation space"), "index"):
        indices = [int(i) for i in re.findall(r"\d+", row[0])]
        cell = row[3].replace("π", "pi")
        low, high = -math.inf, math.inf
        if match := re.search(r"\[(-?[\d.]+), (-?[\d.]+)\]", cell):
            low, high = float(match.group(1)), float(match.group(2))
        elif match := re.search(r"\(-([\d.]+), ([\d.]+)\)", cell):
            low, high = -float(match.group(1)), float(match.group(2))
        elif match := re.search(r"> (-?[\d.]+)", cell):
            low = float(match.group(1))
        elif "0 or 1" in cell:
            low, high = 0.0, 1.0
        for index in indices:
            bounds[index] = (low, high)
    assert sorted(bounds) == list(range(12)), sorted(bounds)
    return bounds


def test_observations_stay_within_the_documented_bounds(address):
    """Random and heuristic landers, the wind on in half of the environments: every value of
    every observation lies within the bounds the Observation table gives."""
    bounds = _observation_bounds()
    low = np.array([bounds[i][0] for i in range(12)])
    high = np.array([bounds[i][1] for i in range(12)])
    rng = np.random.default_rng(0)
    for wind in (False, True):
        vec = mll.vector_env(16, address=address, n_landers=6, enable_wind=wind, terminate_on_damage=False)
        try:
            observations, _ = vec.reset(seed=1)
            seen = [observations.reshape(-1, 12)]
            for step in range(300):
                actions = mll.heuristic(observations)
                wild = rng.random(actions.shape) < (0.5 if step % 50 < 25 else 0.05)
                actions[wild] = rng.integers(0, 4, int(wild.sum()))
                observations, _, _, _, active, _ = vec.step(actions)
                seen.append(observations[active])
        finally:
            vec.close()
        values = np.concatenate(seen)
        assert np.isin(values[:, 6:8], (0.0, 1.0)).all()
        below = values < low
        above = values > high
        assert not below.any() and not above.any(), (
            f"observation values outside the documented bounds at indices "
            f"{sorted(set(np.nonzero(below | above)[1]))}"
        )


# --- Outcomes. ---


def test_outcome_codes_are_the_clients():
    rows = _table(_section("Episode end"), "code")
    assert [(int(code), name) for code, name, *_ in rows] == [
        (code, name or "none") for code, name in enumerate(mll.OUTCOMES)
    ]


# --- Spawn. ---


def _documented_rows(n: int) -> list[int]:
    """Landers per row, top first, for n landers, from the Starting state table."""
    for row in _table(_section("Starting state"), "n_landers"):
        first, _, last = row[0].partition("..")
        first, last = int(first), int(last or first)
        if first <= n <= last:
            if row[2] == "n":
                return [n]
            layouts = [layout.strip() for layout in row[2].split(",")]
            return [int(k) for k in layouts[n - first].split("+")]
    raise AssertionError(f"no spawn row for n_landers={n}")


def test_spawn_positions_are_the_documented_rows(address):
    """After reset (the push moves a lander by a few centimetres), lander j of row r is near
    x = (j + 1) W / (k + 1), y = H - 1.5 r."""
    width, height = 20.0, 40.0 / 3
    for n in range(1, 33):
        env = mll.parallel_env(address=address, n_landers=n)
        try:
            observations, _ = env.reset(seed=n)
        finally:
            env.close()
        rows = _documented_rows(n)
        assert sum(rows) == n
        agent = 0
        for r, k in enumerate(rows):
            for j in range(k):
                o = observations[f"lander_{agent}"]
                x, y = o[0] * width / 2 + width / 2, o[1] * height / 2 + height / 4 + 18 / 30
                assert abs(x - (j + 1) * width / (k + 1)) < 0.2, (n, agent, x)
                assert abs(y - (height - 1.5 * r)) < 0.2, (n, agent, y)
                agent += 1


# --- Rendering. ---


def test_view_constants_are_the_renderers():
    code = _cpp_constants(_RENDERER_H)
    text = _flat(_section("Rendering"))
    scale = code["kFrameHeight"] / (40 / 3 + code["kViewTopMargin"])
    assert scale == pytest.approx(code["kFrameWidth"] / (20 + 2 * code["kViewMarginX"]))
    assert f"{scale:.2f} pixels per meter" in text
    assert f"{code['kViewTopMargin']:g} m" in text
    assert f"{code['kViewMarginX']:.3f} m" in text
    assert f"{code['kFrameWidth']} x {code['kFrameHeight']}" in text


# The scene of the labelled frame: 5 landers, damage ends only the damaged one's episode; the
# outer two hover (main engine while falling, else the heuristic's attitude control), the
# middle three fly Gymnasium's heuristic pilot and meet over the pad. After _FRAME_STEP steps
# (a frame rendered after each, as a viewer would) one has landed, two have crashed, and the
# hovering two fire the main and a side engine.
_FRAME_SEED = 8
_FRAME_STEP = 232
_FRAME_AT = (230, 34)  # Where the frame sits in the labelled image.


def _hover(observation: np.ndarray) -> int:
    action = mll.heuristic(observation)
    if observation[3] < -0.08 and abs(observation[4]) < 0.3:
        return 2
    return action if action != 2 else 0


def reference_frame(address=None) -> tuple[np.ndarray, dict]:
    """The frame, and the world positions (m) of what the labels point at."""
    env = mll.parallel_env(address=address, n_landers=5, terminate_on_damage=False, render_mode="rgb_array")
    try:
        observations, _ = env.reset(seed=_FRAME_SEED)
        ends, actions = {}, {}
        for _ in range(_FRAME_STEP):
            actions = {
                agent: _hover(observations[agent]) if agent in ("lander_0", "lander_4") else mll.heuristic(
                    observations[agent])
                for agent in env.agents
            }
            observations, _, _, _, infos = env.step(actions)
            for agent, info in infos.items():
                if "outcome" in info:
                    ends[agent] = (info["outcome"], observations[agent])
            frame = env.render()
    finally:
        env.close()

    def at(o):
        return (o[0] * 10 + 10, o[1] * 20 / 3 + 10 / 3 + 0.6)

    flying = {agent: at(observations[agent]) for agent in ("lander_0", "lander_4")}
    assert actions == {"lander_0": 2, "lander_4": 3}, actions
    assert sorted(outcome for outcome, _ in ends.values()) == ["crashed", "crashed", "landed"], ends
    landed = next(at(o) for outcome, o in ends.values() if outcome == "landed")
    crashed = [at(o) for outcome, o in ends.values() if outcome == "crashed"]
    return frame, {"main": flying["lander_0"], "side": flying["lander_4"], "landed": landed, "crashed": crashed}


def _to_image(point: tuple[float, float]) -> tuple[float, float]:
    """World meters -> pixel of the labelled image (the renderer's WorldToFrame, then the offset)."""
    scale = 400 / (40 / 3 + 1.5)
    return (point[0] + 1.125) * scale + _FRAME_AT[0], 400 - point[1] * scale + _FRAME_AT[1]


def labelled_frame(frame: np.ndarray, points: dict):
    """The frame on a white canvas, labels beside it with leader lines (Pillow)."""
    from PIL import Image, ImageDraw, ImageFont

    x0, y0 = _FRAME_AT
    image = Image.new("RGB", (x0 + 600 + 250, y0 + 436), "white")
    image.paste(Image.fromarray(frame), _FRAME_AT)
    draw = ImageDraw.Draw(image)
    try:
        font = ImageFont.truetype("/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf", 12)
    except OSError:
        font = ImageFont.load_default()
    ink, lead = (30, 30, 30), (150, 150, 150)

    def label(text: str, y: float, target: tuple[float, float]) -> None:
        """`text` (lines split at |) in the left column when the target is in the left half of
        the frame, else in the right one, level with `y`; a line from it to `target`."""
        left = target[0] < x0 + 300
        edge = x0 - 10 if left else x0 + 610
        lines = text.split("|")
        for k, line in enumerate(lines):
            draw.text((edge, y + 15 * (k - (len(lines) - 1) / 2)), line, fill=ink, font=font,
                      anchor="rm" if left else "lm")
        draw.line([(edge + (4 if left else -4), y), target], fill=lead, width=1)
        draw.ellipse([target[0] - 2.5, target[1] - 2.5, target[0] + 2.5, target[1] + 2.5], fill=(220, 0, 0))

    main, side = _to_image(points["main"]), _to_image(points["side"])
    landed = _to_image(points["landed"])
    crashed = _to_image(points["crashed"][0])
    label("sky", y0 + 40, (x0 + 100, y0 + 50))
    label("lander_0 (Gymnasium's colour)", y0 + 95, (main[0] - 6, main[1]))
    label("main engine: flame|under the body", y0 + 150, (main[0], main[1] + 26))
    label("exhaust particles", y0 + 205, (main[0] - 10, main[1] + 68))
    label("out of bounds (x < 0 m):|shaded strip", y0 + 250, (x0 + 15, y0 + 200))
    label("landed: faint ghost|with a green check", y0 + 330, landed)
    label("moon (ground)", y0 + 385, (x0 + 150, y0 + 350))
    label("side engine (action 3):|flame from the left flank", y0 + 90, (side[0] - 22, side[1] - 12))
    label("lander_4 (its own colour)", y0 + 140, (side[0] + 10, side[1]))
    label("out of bounds (x > 20 m):|shaded strip", y0 + 200, (x0 + 585, y0 + 200))
    label("helipad flags at|x = 8 m and x = 12 m", y0 + 262, (x0 + 356, y0 + 280))
    label("crashed and removed:|grey with a red cross", y0 + 330, (crashed[0] + 6, crashed[1]))
    # The top margin, 1.5 m above the spawn row (y = H), and a scale bar of 2 m.
    scale = 400 / (40 / 3 + 1.5)
    spawn_y = y0 + 400 - (40 / 3) * scale
    draw.line([(x0 + 604, y0), (x0 + 604, spawn_y)], fill=ink, width=2)
    for tick in (y0, spawn_y):
        draw.line([(x0 + 600, tick), (x0 + 608, tick)], fill=ink, width=2)
    draw.text((x0 + 614, (y0 + spawn_y) / 2), "1.5 m margin above the spawn row", fill=ink, font=font, anchor="lm")
    draw.line([(x0, y0 + 418), (x0 + 2 * scale, y0 + 418)], fill=ink, width=2)
    draw.text((x0 + 2 * scale + 8, y0 + 418), "2 m: about 27 pixels per meter", fill=ink, font=font, anchor="lm")
    draw.text((x0, 8), "An rgb_array frame, 600 x 400 (5 landers, step 232)", fill=ink, font=font)
    return image


def test_labelled_frame_is_what_the_renderer_draws(address):
    from PIL import Image

    frame, points = reference_frame(address)
    # Inside the frame the labels draw only lines and dots (no text), so the same labels on
    # today's frame must give the same pixels there.
    x, y = _FRAME_AT
    today = np.asarray(labelled_frame(frame, points))[y:y + 400, x:x + 600].astype(int)
    stored = np.asarray(Image.open(_FRAME_PNG).convert("RGB"))[y:y + 400, x:x + 600].astype(int)
    difference = np.abs(stored - today).mean()
    assert difference < 1.0, (
        f"docs/environment_frame.png differs from today's frame (mean {difference:.2f} per channel); "
        "regenerate it (see this file's docstring) and check the labels and docs/environment.md's Rendering"
    )


if __name__ == "__main__":
    if sys.argv[1:] != ["--write-frame"]:
        sys.exit(__doc__)
    image, where = reference_frame()
    labelled_frame(image, where).save(_FRAME_PNG, optimize=True)
    print(f"wrote {_FRAME_PNG}")
