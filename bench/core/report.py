"""Turns core_bench's JSON output into the Core table of docs/benchmarks.md.

usage: report.py BENCH_JSON BENCHMARKS_MD
Prints the section and replaces the text between the core markers in
BENCHMARKS_MD (appending the section if the markers are absent).
"""
import json
import os
import re
import sys

BEGIN = "<!-- core:begin (bench/core/run.sh writes this section) -->"
END = "<!-- core:end -->"
STEP_TARGET = 1.15  # Env per agent-step <= 1.15 x the bare Box2D floor.
RENDER_TARGET_MS = 1.0


def medians(path):
    with open(path) as f:
        data = json.load(f)
    rows = {}
    for b in data["benchmarks"]:
        if b.get("aggregate_name") == "median":
            rows[b["run_name"]] = b
    return data["context"], rows


def cpu_ms(row):
    scale = {"ns": 1e-6, "us": 1e-3, "ms": 1.0, "s": 1e3}[row["time_unit"]]
    return row["cpu_time"] * scale


def section(context, rows, command):
    lines = [BEGIN, "## Core", ""]
    lines.append(
        f"Command: `{command}` (median of the repetitions, CPU time, "
        f"{context.get('num_cpus')} x {context.get('mhz_per_cpu')} MHz, "
        f"load average at start {', '.join(f'{x:.1f}' for x in context.get('load_avg', []))}; "
        f"run {context.get('date')}).")
    lines.append("")
    lines.append("### Env::Step per agent-step against the bare Box2D floor")
    lines.append("")
    lines.append(
        "Random discrete actions, default config (an episode ends at the first "
        "damage), re-reset when over, resets included. The floor is the same "
        "world built directly in `bench/core/core_bench.cc` (terrain, landers, "
        "legs, revolute joints, collision filters, Gymnasium's engine "
        "impulses, `Step(1/50, 180, 60)`, the Env's spawn layout, same episode "
        "boundaries) without observations, rewards or rules; Env and floor "
        "repetitions are interleaved at random. Target: ratio <= "
        f"{STEP_TARGET}.")
    lines.append("")
    lines.append("| landers | Env us/agent-step | floor us/agent-step | ratio | Env agent-steps/s | target met |")
    lines.append("|---|---|---|---|---|---|")
    for n in (1, 3, 8, 32):
        env = rows.get(f"BM_EnvStep/{n}")
        floor = rows.get(f"BM_FloorStep/{n}")
        if not env or not floor:
            continue
        env_us = 1e6 / env["items_per_second"]
        floor_us = 1e6 / floor["items_per_second"]
        ratio = env_us / floor_us
        lines.append(
            f"| {n} | {env_us:.2f} | {floor_us:.2f} | {ratio:.3f} | "
            f"{env['items_per_second']:,.0f} | {'yes' if ratio <= STEP_TARGET else 'NO'} |")
    lines.append("")
    lines.append("### Reset, rendering, memory")
    lines.append("")
    lines.append("| what | figure |")
    lines.append("|---|---|")
    for n in (1, 3, 8, 32):
        row = rows.get(f"BM_EnvReset/{n}")
        if row:
            lines.append(f"| Env::Reset, n = {n} | {cpu_ms(row) * 1e3:.1f} us |")
    renders_by_name = {name: r for name, r in rows.items() if name.startswith("BM_RenderScene/")}
    for name, render in sorted(renders_by_name.items(),
                               key=lambda item: (item[0].endswith("/1"), item[1].get("landers", 0))):
        ms = cpu_ms(render)
        if name.endswith("/1"):
            # The dashboard's frames: not a raw render, no target.
            lines.append(
                f"| RenderScene with the overlay (text), {render.get('landers', 0):.0f} landers | {ms:.3f} ms |")
            continue
        lines.append(
            f"| RenderScene, {render.get('landers', 0):.0f} landers, "
            f"{render.get('particles', 0):.0f} particles, 600x400 RGB | "
            f"{ms:.3f} ms (target < {RENDER_TARGET_MS} ms: {'met' if ms < RENDER_TARGET_MS else 'NOT met'}) |")
    floor = rows.get("BM_CairoFloor")
    if floor:
        lines.append(
            f"| floor: Cairo alone, 50 antialiased lander bodies on 600x400 | {cpu_ms(floor):.3f} ms "
            f"(RenderScene / floor: "
            + ", ".join(f"{cpu_ms(r) / cpu_ms(floor):.2f} at {r.get('landers', 0):.0f} landers"
                        for name, r in sorted(renders_by_name.items(),
                                              key=lambda item: item[1].get("landers", 0))
                        if name.endswith("/0"))
            + ") |")
    png = rows.get("BM_EncodePng")
    peer = rows.get("BM_EncodePngLibpngDefaults")
    if png:
        lines.append(f"| EncodePng of the 8-lander frame (zlib level 1, no row filter) | {cpu_ms(png):.3f} ms, {png['png_bytes'] / 1024:.1f} KiB |")
    if peer:
        lines.append(f"| libpng defaults (peer, same frame) | {cpu_ms(peer):.3f} ms, {peer['png_bytes'] / 1024:.1f} KiB |")
    for name, row in sorted(rows.items()):
        m = re.match(r"BM_MemoryPerEnv/(\d+)/(\d+)", name)
        if m:
            lines.append(
                f"| heap per Env after Reset, n = {m.group(1)} ({m.group(2)} envs, mallinfo2) | "
                f"{row['env_kb']:.0f} KiB (bare Box2D floor world: {row['floor_kb']:.0f} KiB) |")
    lines.append("")
    lines.append(
        "RenderScene antialiases everything but the particles (Cairo's FAST "
        "antialiasing; each lander's outline and fill are two fills of its "
        "three parts, all flames two fills). Its floor only fills 50 "
        "polygons: RenderScene also draws the sky, the margins, particles, "
        "flames, marks and flags, and converts the surface to packed RGB "
        "(about a third of its instructions under callgrind). The overlay "
        "adds text for the dashboard's frames. EncodePng uses zlib level 1 and "
        "no row filter; the peer row is libpng's simplified writer with its "
        "defaults on the same frame. Heap per Env is mallinfo2's in-use bytes "
        "over many Envs, nearly all of it Box2D's own allocator (compare the "
        "bare floor world).")
    lines.append(END)
    return "\n".join(lines) + "\n"


def main():
    context, rows = medians(sys.argv[1])
    text = section(context, rows, os.environ.get("COMMAND", "bench/core/run.sh"))
    print(text)
    doc_path = sys.argv[2]
    doc = open(doc_path).read() if os.path.exists(doc_path) else "# Benchmarks\n\n"
    if BEGIN in doc and END in doc:
        head, rest = doc.split(BEGIN, 1)
        tail = rest.split(END, 1)[1].lstrip("\n")
        doc = head + text + ("\n" + tail if tail else "")
    else:
        doc = doc.rstrip("\n") + "\n\n" + text
    with open(doc_path, "w") as f:
        f.write(doc)


if __name__ == "__main__":
    main()
