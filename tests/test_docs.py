"""The documentation: the site builds with `mkdocs build --strict` (no broken link or anchor,
no page left out of the navigation), its generated references list exactly the settings of
`Config` and the commands of the command line, and the README stays a small front page whose
links resolve and whose command list names only real commands and options."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
README_MAX_BYTES = 10_240
# The classes docs/hooks.py gives the anchor of each setting and each command.
SETTING_CLASS = "dqnlab-setting"
COMMAND_CLASS = "dqnlab-command"


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site built once into a temporary directory (about a second)."""
    for module in ("mkdocs", "material"):
        pytest.importorskip(
            module, reason="the docs tools are not installed: pip install -e '.[docs]'"
        )
    out = tmp_path_factory.mktemp("site")
    environment = {
        **os.environ,
        "NO_MKDOCS_2_WARNING": "1",  # mkdocs-material's banner, not a warning of the build
        "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)]
    built = subprocess.run(
        command, cwd=ROOT, env=environment, capture_output=True, text=True, timeout=300
    )
    warnings = [line for line in built.stderr.splitlines() if line.startswith("WARNING")]
    assert built.returncode == 0 and not warnings, built.stderr[-5000:]
    return out


def test_the_site_builds_with_no_warning(site: Path) -> None:
    assert (site / "index.html").is_file()
    assert (site / "settings" / "index.html").is_file()
    assert (site / "commands" / "index.html").is_file()


def test_the_settings_page_lists_every_field_of_config_once_and_nothing_else(site: Path) -> None:
    from dqnlab.config import Config

    listed = _ids_of_class(site / "settings" / "index.html", SETTING_CLASS)
    assert sorted(listed) == sorted(f.name for f in dataclasses.fields(Config))


def test_the_commands_page_lists_every_command_and_its_options(site: Path) -> None:
    """Every command, a group's subcommands in its place (`dqnlab bench gpu`: `bench-gpu`)."""
    group, ctx = _cli()
    commands = list(_leaf_commands(group, ctx))
    page = site / "commands" / "index.html"
    ids = [path.replace(" ", "-") for path, _, _ in commands]
    assert sorted(_ids_of_class(page, COMMAND_CLASS)) == sorted(ids)
    text = page.read_text()
    for path, command, parent in commands:
        for option in _option_names(command, parent):
            assert f"<code>{option}</code>" in text, f"{path} {option}"


def test_readme_is_a_small_front_page() -> None:
    size = len(README.read_bytes())
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes; move detail into docs/"
    text = README.read_text()
    # CI (.ci/run) runs the test command the README names; the main job is training Pong.
    assert "make test" in text and "make train GAME=pong" in text


def test_every_relative_link_in_the_readme_points_at_a_file() -> None:
    text = README.read_text()
    inline = re.findall(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text)
    definitions = re.findall(r"^\s*\[[^\]]+\]:\s*<?(\S+?)>?(?:\s|$)", text, re.MULTILINE)
    relative = [
        link
        for link in inline + definitions
        if not re.match(r"[a-z][a-z0-9+.-]*:", link) and not link.startswith("#")
    ]
    assert relative, "the README links into docs/"
    missing = [link for link in relative if not (ROOT / link.split("#")[0]).exists()]
    assert not missing, f"README.md links to missing files: {missing}"


def test_the_readme_command_list_names_only_real_commands_and_options() -> None:
    """The README's block of `dqnlab COMMAND ...` lines names every command and no option the
    command does not have (it may leave options out: the command reference has them all)."""
    group, ctx = _cli()
    blocks = re.findall(r"^```[\w-]*\n(.*?)^```", README.read_text(), re.DOTALL | re.MULTILINE)
    block = next(b for b in blocks if b.startswith("dqnlab train"))
    commands = {path: (command, parent) for path, command, parent in _leaf_commands(group, ctx)}
    options: dict[str, set[str]] = {}
    path = ""
    for line in block.splitlines():
        if line.startswith("dqnlab "):
            words = line.split()  # `dqnlab COMMAND`, or `dqnlab GROUP SUBCOMMAND`
            path = words[1] if words[1] in commands else " ".join(words[1:3])
            assert path in commands, f"README: no command dqnlab {path}"
            options.setdefault(path, set())
        options[path] |= set(re.findall(r"--[a-z][a-z0-9-]*", line.split("#")[0]))
    visible = [n for n in group.list_commands(ctx) if not group.get_command(ctx, n).hidden]
    assert sorted({path.split()[0] for path in options}) == sorted(visible)
    for path, named in options.items():
        unknown = named - set(_option_names(*commands[path]))
        assert not unknown, f"README: dqnlab {path} has no option {sorted(unknown)}"


def _cli() -> tuple[Any, Any]:
    """The `dqnlab` click group and a context for it."""
    import typer.main

    from dqnlab.cli import app

    group = typer.main.get_command(app)
    return group, group.make_context("dqnlab", [], resilient_parsing=True)


def _leaf_commands(group: Any, ctx: Any, prefix: str = "") -> Iterator[tuple[str, Any, Any]]:
    """(name after `dqnlab`, command, its group's context) of every visible command, a
    group's subcommands in its place, as docs/hooks.py lists them."""
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        path = f"{prefix} {name}".strip()
        if command.hidden:
            continue
        if hasattr(command, "list_commands"):
            sub_ctx = command.make_context(name, [], parent=ctx, resilient_parsing=True)
            yield from _leaf_commands(command, sub_ctx, path)
        else:
            yield path, command, ctx


def _option_names(command: Any, ctx: Any) -> list[str]:
    sub_ctx = command.make_context(command.name, [], parent=ctx, resilient_parsing=True)
    help_option = command.get_help_option(sub_ctx)
    return [
        name
        for param in command.get_params(sub_ctx)
        if param.param_type_name == "option" and param is not help_option and not param.hidden
        for name in [*param.opts, *param.secondary_opts]
    ]


def _ids_of_class(page: Path, css_class: str) -> list[str]:
    """The ids of the page's elements of class `css_class`, in page order."""
    parser = _IdsOfClass(css_class)
    parser.feed(page.read_text())
    return parser.found


class _IdsOfClass(HTMLParser):
    def __init__(self, css_class: str) -> None:
        super().__init__()
        self.css_class = css_class
        self.found: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        attributes = dict(attrs)
        if self.css_class in (attributes.get("class") or "").split():
            self.found.append(attributes.get("id") or "")
