"""The documentation against the product (acceptance probe, session 36).

An acceptance tester reads README.md, ARCHITECTURE.md and docs/*.md and types what they say.
What this pass found the docs (or the --help text) to say otherwise than the code:

1. `--help`: ten options said nothing (`client --server/--name`, `bot --server/--profile`,
   `view --server/--frames/--out/--name`, `render/view --no-fog`), and `sortie terrain`,
   `sortie fdm` and `sortie demo` described less than they do (the demo's was its module
   docstring's first line, ``sortie demo``: in reST quotes).
2. ARCHITECTURE.md's limit tables: the simulation server's concurrent RPCs were "256 x 7 =
   1,792" (the code: 256 x 8 = 2,048, the eight calls the row lists), and `MAX_LOS_RAYS` /
   `MAX_SEGMENTS` were placed in terrain/profile.py (they are server/terrain_service.py's).
3. docs/RECORDING.md said chunk bodies are zstd level 3; the writer uses level 1.
4. docs/STORE.md's list of store.json keys left out `quadtree`, which every import writes.
5. docs/DEPLOYMENT.md's image left out `libgl1` and the `/frames` volume, and its volume table
   the compose file's named volume `frames`.
6. README.md's Recording example named a file no server writes for the example scenario.
"""

from __future__ import annotations

import argparse
import importlib
import re
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
NUM = r"\d[\d,]*(?:\.\d+)?"


# -- 1. every command and option says what it does -------------------------------------------

def _walk(parser: argparse.ArgumentParser, path: list[str]):
    """(command path, parser, sub-command help) of every sub-command under ``parser``."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                yield path + [name], sub, helps.get(name)
                yield from _walk(sub, path + [name])


def test_every_command_and_option_says_what_it_does():
    from sortie.cli import build_parser

    missing = []
    commands = list(_walk(build_parser(), ["sortie"]))
    assert len(commands) >= 29  # every command and sub-command of the one CLI
    for path, parser, help_line in commands:
        if not help_line:
            missing.append(f"{' '.join(path)} (its line in its parent's --help)")
        if not parser.description or "``" in parser.description:
            missing.append(f"{' '.join(path)} (description: {parser.description!r})")
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            if not (action.help or "").strip():
                missing.append(f"{' '.join(path)} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, "says nothing: " + "; ".join(missing)


def test_group_commands_name_every_sub_command_in_their_description():
    from sortie.cli import build_parser

    for path, parser, _ in _walk(build_parser(), ["sortie"]):
        subs = next((a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if subs and len(path) == 2:
            for name in subs:
                assert re.search(rf"\b{name}\b", parser.description, re.I), (path, name, parser.description)


# -- 2. ARCHITECTURE.md's limit tables name the code's values -----------------------------------

def _limit_rows(text: str):
    """(value, module path, constant) of each row of a "| limit | value | where |" table that
    names one constant; a row without a path takes the previous row's (the table's style)."""
    for table in text.split("\n\n"):
        lines = [line for line in table.splitlines() if line.startswith("| ")]
        if not lines or not lines[0].startswith("| limit | value | where |"):
            continue
        path = None
        for line in lines[2:]:
            cells = [c.strip() for c in line.strip().strip("|").split(" | ")]
            if len(cells) != 3:
                continue
            names = re.findall(r"`([^`]+)`", cells[2])
            path = next((n for n in names if n.endswith(".py")), path)
            consts = [n for n in names if re.fullmatch(r"[A-Z][A-Z0-9_]+", n)]
            if len(consts) == 1 and path is not None:
                yield cells[1], path, consts[0]


def _number(value: str) -> float | None:
    """The one number a value cell states ("4", "64 MiB", "256 x 8 = 2,048", "120 s, then ...",
    "≤ 60 Hz (default 10)"); None for ranges, lists and prose."""
    if re.search(r"/|, \d|–", value):
        return None
    m = re.fullmatch(rf"(?:≤ )?(?:\d+ x \d+ = )?({NUM})(?: (MiB|GiB))?(?:[ (].*)?", value)
    if m is None:
        return None
    return float(m.group(1).replace(",", "")) * {None: 1, "MiB": 1 << 20, "GiB": 1 << 30}[m.group(2)]


def test_architecture_limit_tables_match_the_code():
    checked, wrong = 0, []
    for value, path, const in _limit_rows((REPO / "ARCHITECTURE.md").read_text()):
        stated = _number(value)
        if stated is None:
            continue
        module = importlib.import_module(path[:-3].replace("/", "."))
        actual = getattr(module, const, None)
        checked += 1
        if actual is None or float(actual) != stated:
            wrong.append(f"{path} {const}: the table says {value!r}, the code {actual!r}")
    assert checked >= 25  # the parser still reads the tables
    assert not wrong, wrong


# -- 3. docs/RECORDING.md: the chunk body's zstd level -------------------------------------------

def test_recording_md_states_the_writers_zstd_level():
    from server.recording import ZSTD_LEVEL

    text = (REPO / "docs" / "RECORDING.md").read_text()
    levels = re.findall(r"\*\*ChunkBody\*\* \(zstd level (\d+)", text)
    assert levels == [str(ZSTD_LEVEL)]


# -- 4. docs/STORE.md: every key store.json has --------------------------------------------------

def test_store_md_lists_every_key_an_import_writes(tmp_path):
    import json

    from sortie.cli import main

    store = tmp_path / "store"
    dem = REPO / "data" / "dem" / "landlab_SRTMGL3_BoulderCO_553x553.asc"
    assert main(["terrain", "import", str(dem), "-o", str(store), "--resolution", "6", "--no-progress"]) == 0
    manifest = json.loads((store / "store.json").read_text())
    text = (REPO / "docs" / "STORE.md").read_text()
    section = text[text.index("**`store.json`** has these keys:"):text.index("A reader opens the manifest")]
    documented = set(re.findall(r"`([a-z_0-9]+)`", section))
    assert set(manifest) - documented == set()
    assert set(manifest["regions"][0]) - documented == set()


# -- 5. docs/DEPLOYMENT.md: the image and the volumes ---------------------------------------------

def test_deployment_md_names_the_images_packages_and_volumes():
    import yaml

    doc = (REPO / "docs" / "DEPLOYMENT.md").read_text()
    dockerfile = (REPO / "Dockerfile").read_text()
    runtime = dockerfile[dockerfile.index("AS runtime"):]
    apt = re.search(r"apt-get install -y --no-install-recommends \\\s*\n\s*([^\\]+)\\", runtime).group(1).split()
    image = doc[doc.index("## The image"):doc.index("## Services")]
    listed = re.search(r"headless OpenGL \(`([^`]+)`", image).group(1).split()
    assert listed == apt
    volumes = re.search(r'VOLUME \["([^\]]+)"\]', runtime).group(1).split('", "')
    assert f"`VOLUME {' '.join(volumes)}`" in image
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    table = doc[doc.index("## Volumes"):doc.index("## Health checks")]
    for name in compose["volumes"]:
        assert f"| `{name}` (named) |" in table, name


# -- 6. README.md: the Recording example's file name ----------------------------------------------

def test_readme_recording_example_is_named_as_the_server_names_it():
    from server.sim_cli import recording_slug

    scenario = tomllib.loads((REPO / "data" / "scenarios" / "alps.toml").read_text())
    slug = recording_slug(scenario["exercise"]["name"])
    names = re.findall(r'Recording\("recordings/([^"]+)"\)', (REPO / "README.md").read_text())
    assert names and all(re.fullmatch(rf"{re.escape(slug)}-\d{{8}}T\d{{6}}Z\.sortie", n) for n in names), (slug, names)


@pytest.mark.parametrize("option", ["--store", "--procedural", "--address"])
def test_readme_terrain_info_row_names_every_terrain_option(option):
    """README's command table gives `sortie terrain info` the terrain options its parser takes
    (it said `--dem FILE...` alone)."""
    row = next(line for line in (REPO / "README.md").read_text().splitlines()
               if line.startswith("| `sortie terrain info"))
    assert option in row.split("` |")[0]
