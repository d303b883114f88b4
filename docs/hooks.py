"""MkDocs hook: the settings and command references, generated from the code at each build.

`settings.md` lists every field of `dqnlab.config.Config` with its type, its value in each
shipped preset and its doc, grouped under the comments that group the fields in `Config`.
`commands.md` renders every command of the `dqnlab` command line from its own help: usage,
help text, arguments and options. Neither page exists on disk, so neither can go stale; a
hand-written page links to `settings.md#NAME` or `commands.md#NAME`, and with
`validation: anchors: warn` and `mkdocs build --strict` a link to a setting or command that
no longer exists fails the build.
"""

from __future__ import annotations

import ast
import dataclasses
import html
import inspect
import itertools
import re
import typing
from collections.abc import Iterator
from typing import Any

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

SETTINGS_PAGE = "settings.md"
COMMANDS_PAGE = "commands.md"
# Classes of the anchors the pages give each setting and command (tests/test_docs.py reads them).
SETTING_CLASS = "dqnlab-setting"
COMMAND_CLASS = "dqnlab-command"
PRESET_CLASS = "dqnlab-preset"  # a preset's name, never broken at its hyphen (extra.css)
UNGROUPED = "Settings"


def on_files(files: Files, config: MkDocsConfig) -> Files:
    """Add the two generated pages to the site before its navigation is built."""
    files.append(File.generated(config, SETTINGS_PAGE, content=settings_page()))
    files.append(File.generated(config, COMMANDS_PAGE, content=commands_page()))
    return files


# Settings ---------------------------------------------------------------------------------


def settings_page() -> str:
    from dqnlab.config import Config, load_preset, preset_names

    presets = {name: load_preset(name) for name in preset_names()}
    hints = typing.get_type_hints(Config)
    lines = [
        "# Settings",
        "",
        "Every setting of a run, generated from `dqnlab.config.Config` when this site is "
        "built: its type, its value in each shipped preset (a preset file that leaves a "
        "setting out gets `Config`'s default) and what it means. Override any of them with "
        "`--set KEY=VALUE` or in a preset file of your own ([Presets](presets.md)); "
        "[The nature preset](nature.md) gives the source of each nature value.",
    ]
    lines += ["", "## Presets", "", _row(["preset", "what its file says"]), _row(["---", "---"])]
    lines += [_row([_preset(name), _plain(preset_description(name), True)]) for name in presets]
    header = ["setting", "type", "value in each preset", "meaning"]
    for group, fields in field_groups(Config).items():
        title, _, remark = group.partition(" (")
        lines += ["", f"## {title}", ""]
        if remark:  # "Speed (no change of results ...)": the remark goes under the heading
            remark = remark.removesuffix(")")
            lines += [remark[:1].upper() + remark[1:] + ".", ""]
        lines += [_row(header), _row(["---"] * len(header))]
        for f in fields:
            anchor = f'<a id="{f.name}" class="{SETTING_CLASS}" href="#{f.name}">`{f.name}`</a>'
            values = {name: preset.get(f.name, _default(f)) for name, preset in presets.items()}
            doc = _plain(f.metadata["doc"])
            lines.append(_row([anchor, _type_text(hints[f.name]), _preset_values(values), doc]))
    return "\n".join(lines + part_settings_section()) + "\n"


# Where parts that declare settings of their own (`SETTINGS`) are looked for: the shipped
# part modules and the repository's examples.
PART_MODULES = (
    "dqnlab.algorithm.losses", "dqnlab.algorithm.heads", "dqnlab.algorithm.policies",
    "dqnlab.algorithm.augmentation",
)  # fmt: skip


def part_settings_section() -> list[str]:
    """The settings each part declares (`dqnlab.parts.PartSetting`), a table per part, set
    as `parts.SETTING.NAME`: the shipped parts' and the examples' (`examples/*.py`)."""
    import importlib
    import sys
    from pathlib import Path

    from dqnlab.parts import PartSetting

    root = Path(__file__).resolve().parents[1]
    if str(root) not in sys.path:
        sys.path.insert(0, str(root))
    examples = sorted(f"examples.{path.stem}" for path in (root / "examples").glob("[!_]*.py"))
    lines = [
        "",
        "## Parts' own settings",
        "",
        "Settings a part declares for itself (`SETTINGS`, a dict of `dqnlab.parts."
        "PartSetting`; [Your own variant](own-variant.md#a-parts-own-settings)), set as "
        "`--set parts.PART.NAME=VALUE` or under `[parts.PART]` in a TOML file, where PART is "
        "the setting naming the part (`loss`, `head`...). Found in the shipped parts' modules "
        "and the repository's `examples/` when this site is built.",
    ]
    header = ["part", "setting", "type", "default", "meaning"]
    rows = []
    for name in PART_MODULES + tuple(examples):
        module = importlib.import_module(name)
        for attribute, part in sorted(vars(module).items()):
            declared = getattr(part, "SETTINGS", None)
            if getattr(part, "__module__", None) != name or not isinstance(declared, dict):
                continue
            for key, spec in declared.items():
                if isinstance(spec, PartSetting):
                    rows.append(
                        [f"`{name}:{attribute}`", f"`{key}`", type(spec.default).__name__,
                         f"`{_value_text(spec.default)}`", _plain(spec.doc)]
                    )  # fmt: skip
    if not rows:
        return lines + ["", "No part declares settings yet."]
    return lines + ["", _row(header), _row(["---"] * len(header))] + [_row(r) for r in rows]


def preset_description(name: str) -> str:
    """The comment block that opens a shipped preset's file, as one line."""
    from importlib import resources

    text = (resources.files("dqnlab") / "presets" / f"{name}.toml").read_text()
    comments = itertools.takewhile(lambda line: line.startswith("#"), text.splitlines())
    return " ".join(line.lstrip("#").strip() for line in comments)


def field_groups(cls: type) -> dict[str, list[dataclasses.Field[Any]]]:
    """The dataclass's fields under the comment line above each run of them in its source
    (`# Replay memory.`), in source order; all under one heading if the source is missing."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    groups: dict[str, list[dataclasses.Field[Any]]] = {}
    try:
        source = inspect.getsource(cls)
    except (OSError, TypeError):
        return {UNGROUPED: list(fields.values())}
    lines = source.splitlines()
    body = ast.parse(source).body[0]
    assert isinstance(body, ast.ClassDef)
    group, previous_end = UNGROUPED, body.lineno
    for node in body.body:
        comments = [line.strip() for line in lines[previous_end : node.lineno - 1]]
        comments = [c.lstrip("#").strip() for c in comments if c.startswith("#")]
        if comments:
            group = " ".join(comments).removesuffix(".")
        previous_end = node.end_lineno or node.lineno
        target = node.target if isinstance(node, ast.AnnAssign) else None
        if isinstance(target, ast.Name) and target.id in fields:
            groups.setdefault(group, []).append(fields.pop(target.id))
    if fields:  # fields the class body does not declare itself (inherited ones)
        groups.setdefault(UNGROUPED, []).extend(fields.values())
    return groups


def _preset_values(values: dict[str, Any]) -> str:
    """Each value and the presets that give it, one per line: `4` in every preset, or
    `1_000_000`: machado, nature / `100_000`: classic."""
    presets_by_value: dict[str, list[str]] = {}
    for preset, value in values.items():
        presets_by_value.setdefault(_value_text(value), []).append(preset)
    if len(presets_by_value) == 1:
        return f"`{next(iter(presets_by_value))}` in every preset"
    return "<br>".join(
        f"`{value}`: {', '.join(_preset(name) for name in names)}"
        for value, names in presets_by_value.items()
    )


def _preset(name: str) -> str:
    return f'<span class="{PRESET_CLASS}">{name}</span>'


def _default(f: dataclasses.Field[Any]) -> Any:
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def _value_text(value: Any) -> str:
    """A value as a preset file writes it (TOML), long integers with `_` as the presets do."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value:_}" if abs(value) >= 10_000 else str(value)
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value_text(v) for v in value) + "]"
    if isinstance(value, dict):  # an inline table
        return "{" + ", ".join(f"{k} = {_value_text(v)}" for k, v in value.items()) + "}"
    return repr(value)


def _type_text(hint: Any) -> str:
    return hint.__name__ if isinstance(hint, type) else str(hint).replace("typing.", "")


def _plain(text: str, code_spans: bool = False) -> str:
    """Plain text (a `Config` doc, written for `--help`) made safe inside a Markdown table;
    with `code_spans`, text in backquotes stays code."""
    if code_spans:
        parts = re.split(r"(`[^`]+`)", text)
        return "".join(part if part.startswith("`") else _plain(part) for part in parts)
    return re.sub(r"([\\`*_\[\]|])", r"\\\1", html.escape(text, quote=False))


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


# Commands ---------------------------------------------------------------------------------
# The objects below are click's, or those of the copy of click that typer ships since 0.2x;
# only the API both share is used, hence `Any`.


def commands_page() -> str:
    import typer.main

    from dqnlab.cli import app

    group = typer.main.get_command(app)
    root = group.make_context("dqnlab", [], resilient_parsing=True)
    commands = list(walk_commands(group, root))
    lines = [
        "# Commands",
        "",
        "Generated from the `dqnlab` command line when this site is built: the same usage, "
        "help and options as `dqnlab COMMAND --help` prints.",
        "",
        "```",
        group.get_usage(root),
        "```",
        "",
        _help_text(group),
        "",
        _row(["command", "what it does"]),
        _row(["---", "---"]),
        *(_row([f"[`{path}`](#{_anchor(path)})", _summary(cmd)]) for path, cmd, _ in commands),
    ]
    for path, cmd, ctx in commands:
        lines += ["", f"## {path} {{#{_anchor(path)} .{COMMAND_CLASS}}}", ""]
        lines += ["```", cmd.get_usage(ctx), "```", "", _help_text(cmd), ""]
        help_option = cmd.get_help_option(ctx)
        params = [p for p in cmd.get_params(ctx) if p is not help_option and not p.hidden]
        if params:
            lines += [_row(["argument or option", "type", "default", "meaning"])]
            lines += [_row(["---"] * 4), *(_row(_param_cells(p, ctx)) for p in params)]
    return "\n".join(lines) + "\n"


def walk_commands(group: Any, ctx: Any) -> Iterator[tuple[str, Any, Any]]:
    """(name after `dqnlab`, command, its context) of every visible command, subgroups'
    commands included, in the order `--help` lists them."""
    for name in group.list_commands(ctx):
        cmd = group.get_command(ctx, name)
        if cmd is None or cmd.hidden:
            continue
        sub_ctx = cmd.make_context(name, [], parent=ctx, resilient_parsing=True)
        path = f"{ctx.command_path.removeprefix('dqnlab').strip()} {name}".strip()
        if hasattr(cmd, "list_commands"):
            yield from walk_commands(cmd, sub_ctx)
        else:
            yield path, cmd, sub_ctx


def _anchor(path: str) -> str:
    return path.replace(" ", "-")


def _help_text(cmd: Any) -> str:
    """The command's help as `--help` shows it: Markdown (the app's rich_markup_mode)."""
    return inspect.cleandoc(cmd.help or "").split("\f")[0].strip()


def _summary(cmd: Any) -> str:
    return " ".join(_help_text(cmd).split("\n\n")[0].split()).replace("|", "\\|")


def _param_cells(param: Any, ctx: Any) -> list[str]:
    if param.param_type_name == "argument":  # named as its --help names it
        record = param.get_help_record(ctx)
        name = f"`{record[0].split()[0] if record else param.name.upper()}`"
    else:
        name = " / ".join(f"`{opt}`" for opt in [*param.opts, *param.secondary_opts])
    help_text = (getattr(param, "help", None) or "").replace("|", "\\|")
    return [name, _param_type(param, ctx), _param_default(param), help_text]


def _param_type(param: Any, ctx: Any) -> str:
    if getattr(param, "is_flag", False):
        return "flag"
    display_type = getattr(param, "display_type", None)  # typer's own click
    text = display_type(ctx) if callable(display_type) else param.type.name  # click
    return html.escape(str(text).strip("<>"))


def _param_default(param: Any) -> str:
    default = param.default
    if param.required:
        return "required"
    if getattr(param, "is_flag", False):
        if param.secondary_opts:
            return f"`{param.opts[0] if default else param.secondary_opts[0]}`"
        return "on" if default else "off"
    if default is None or default == () or default == []:
        return ""
    if callable(default):
        return "computed"
    return f"`{default}`"
