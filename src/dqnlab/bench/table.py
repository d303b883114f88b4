"""The throughput table of `dqnlab bench envs`, in Markdown: one row per
(number of environments, concurrency) and per peer, then the update against the matrix
multiply and, when measured, the stop checkpoint, each with its target (issue 22)."""

from __future__ import annotations

from typing import Any

# Issue 22's targets on a CPU: training frames/s against each peer's, and the update's
# share of this machine's dense matrix-multiply throughput.
TARGET_RATIO_VS_PEER = 1.8
TARGET_FRACTION_OF_MATMUL = 0.75


def _row_label(key: str) -> str:
    """`num_envs_8_actor_learner` -> "dqnlab, num_envs 8, actor-learner"."""
    rest = key.removeprefix("num_envs_")
    count, _, mode = rest.partition("_")
    return f"dqnlab, num_envs {count}" + (f", {mode.replace('_', '-')}" if mode else "")


def _ratio(figures: dict[str, Any], name: str) -> str:
    value = figures.get(name)
    return "" if value is None else f"{value:.2f}"


def _peers(figures: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(key, column title, row label) of each peer measured."""
    peers = (
        ("sb3", "SB3", f"Stable-Baselines3 {figures.get('peer_version', '')}".strip()),
        ("cleanrl", "CleanRL", f"CleanRL dqn_atari.py @ {str(figures.get('cleanrl_commit'))[:8]}"),
    )
    return [peer for peer in peers if f"{peer[0]}_train_frames_per_second" in figures]


def _rounds(figures: dict[str, Any], key: str) -> str:
    return ", ".join(f"{f:.1f}" for f in figures[f"{key}_train_frames_per_second_runs"])


def _rows(figures: dict[str, Any]) -> list[str]:
    peers = _peers(figures)
    keys = [
        name.removesuffix("_train_frames_per_second")
        for name in figures
        if name.startswith("num_envs_") and name.endswith("_train_frames_per_second")
    ]
    rows = [
        "| run | frames/s | rounds | × num_envs 1 |" + "".join(f" × {p[1]} |" for p in peers),
        "|---|---:|---|---:|" + "---:|" * len(peers),
    ]
    for key in keys:
        ratios = [f"{key}_ratio_vs_1", *(f"{key}_ratio_vs_{peer[0]}" for peer in peers)]
        rows.append(
            f"| {_row_label(key)} | {figures[f'{key}_train_frames_per_second']:.1f} "
            f"| {_rounds(figures, key)} |" + "".join(f" {_ratio(figures, r)} |" for r in ratios)
        )
    for peer, _, label in peers:
        rows.append(
            f"| {label} | {figures[f'{peer}_train_frames_per_second']:.1f} "
            f"| {_rounds(figures, peer)} |" + " |" * (1 + len(peers))
        )
    return rows


def _met(ok: bool) -> str:
    return "met" if ok else "NOT met"


def format_table(figures: dict[str, Any]) -> str:
    """The figures of `vector.measure_num_envs` (and of `checkpoint.measure_stop_checkpoint`
    when present) as a Markdown table and the lines under it."""
    lines = [
        f"Training frames/s, {figures['env']}, nature preset, ε = 0.1, "
        f"{figures['steps']} agent steps per round, {figures['rounds']} alternating rounds, "
        f"{figures['threads']} threads (load {figures['load_average_1min']:.2f} at the start)",
        "",
        *_rows(figures),
        "",
    ]
    for peer, name in (("sb3", "SB3"), ("cleanrl", "CleanRL")):
        ratio = figures.get(f"num_envs_1_ratio_vs_{peer}")
        if ratio is not None:
            lines.append(
                f"- exact loop (num_envs 1) against {name}: {ratio:.2f}× "
                f"(target ≥ {TARGET_RATIO_VS_PEER}×: {_met(ratio >= TARGET_RATIO_VS_PEER)})"
            )
    fraction = figures["update_fraction_of_matmul"]
    lines.append(
        f"- update: {figures['update_ms']:.2f} ms = {figures['update_gflop_per_s']:.1f} GFLOP/s; "
        f"{figures['matmul_size']}² float32 matmul on {figures['matmul_threads']} threads: "
        f"{figures['matmul_gflop_per_s']:.1f} GFLOP/s; fraction {fraction:.3f} "
        f"(target ≥ {TARGET_FRACTION_OF_MATMUL}: {_met(fraction >= TARGET_FRACTION_OF_MATMUL)})"
    )
    for codec in ("none", "lz4"):
        seconds = figures.get(f"checkpoint_stop_seconds_{codec}")
        if seconds is None:
            continue
        megabytes = figures[f"checkpoint_stop_bytes_{codec}"] / 1e6
        lines.append(
            f"- stop checkpoint after {figures['checkpoint_steps']:,} steps "
            f"(replay_compression = {codec}): {megabytes:.1f} MB in {seconds:.2f} s "
            f"(targets ≤ {figures['checkpoint_target_bytes'] / 1e6:.0f} MB and "
            f"≤ {figures['checkpoint_target_seconds']:g} s: "
            f"{_met(figures[f'checkpoint_stop_within_targets_{codec}'])})"
        )
    return "\n".join(lines)
