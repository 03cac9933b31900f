"""Turns core_bench's JSON output into the core rows of docs/benchmarks.md.

usage: report.py BENCH_JSON
Prints the rows of run A in the table's format (what | ours | floor, same
run | ratio | target | run), then the run's context (CPUs, load average), for
the doc to be updated by hand: the table mixes runs of several benchmarks.
"""
import json
import sys

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


def us_per_item(row):
    return 1e6 / row["items_per_second"]


def table_rows(rows, run):
    """The table's rows made by core_bench, each a list of its six cells."""
    out = []
    for n in (1, 3, 8, 32):
        env, floor = rows.get(f"BM_EnvStep/{n}"), rows.get(f"BM_FloorStep/{n}")
        if not env or not floor:
            continue
        what = ("`Env::Step`, 1 lander, per agent-step (CPU)" if n == 1
                else f"`Env::Step`, {n} landers")
        floor_text = (f"bare Box2D world: {us_per_item(floor):.2f} us" if n == 1
                      else f"{us_per_item(floor):.2f} us")
        out.append([what, f"{us_per_item(env):.2f} us", floor_text,
                    f"{us_per_item(env) / us_per_item(floor):.3f}",
                    f"<= {STEP_TARGET}", run])

    resets = [(n, rows[f"BM_EnvReset/{n}"]) for n in (3, 32) if f"BM_EnvReset/{n}" in rows]
    if resets:
        out.append([f"`Env::Reset`, {' / '.join(str(n) for n, _ in resets)} landers",
                    " / ".join(f"{cpu_ms(r) * 1e3:.1f}" for _, r in resets) + " us",
                    "", "", "", run])

    # BM_RenderScene/<landers asked>/<overlay>; the counters give the landers
    # and particles the scene actually held.
    def renders(overlay):
        found = [r for name, r in rows.items()
                 if name.startswith("BM_RenderScene/") and name.endswith(f"/{overlay}")]
        return sorted(found, key=lambda r: r.get("landers", 0))

    plain, overlaid = renders(0), renders(1)
    cairo = rows.get("BM_CairoFloor")
    if plain:
        scenes = " / ".join(f"{r.get('landers', 0):.0f} landers and {r.get('particles', 0):.0f} particles"
                            for r in plain)
        slowest = max(cpu_ms(r) for r in plain)
        out.append([f"frame (`RenderScene` 600x400 RGB), {scenes}",
                    " / ".join(f"{cpu_ms(r):.3f}" for r in plain) + " ms",
                    f"Cairo alone, 50 antialiased lander bodies: {cpu_ms(cairo):.3f} ms" if cairo else "",
                    " / ".join(f"{cpu_ms(r) / cpu_ms(cairo):.1f}" for r in plain) if cairo else "",
                    f"< {RENDER_TARGET_MS:g} ms" + ("" if slowest < RENDER_TARGET_MS else " (NOT met)"),
                    run])
    if overlaid:
        out.append(["the same frames with the overlay (step, ids, returns, outcomes)",
                    " / ".join(f"{cpu_ms(r):.3f}" for r in overlaid) + " ms", "", "", "", run])

    png, peer = rows.get("BM_EncodePng"), rows.get("BM_EncodePngLibpngDefaults")
    if png:
        out.append(["PNG of a frame (8 landers)",
                    f"{cpu_ms(png):.2f} ms, {png['png_bytes'] / 1024:.1f} KiB",
                    f"libpng's defaults: {cpu_ms(peer):.2f} ms, {peer['png_bytes'] / 1024:.1f} KiB" if peer else "",
                    f"{cpu_ms(png) / cpu_ms(peer):.2f}" if peer else "", "", run])

    # BM_MemoryPerEnv/<landers>/<envs>.
    memory = sorted((int(name.split("/")[1]), r) for name, r in rows.items()
                    if name.startswith("BM_MemoryPerEnv/") and int(name.split("/")[1]) in (3, 32))
    if memory:
        out.append([f"heap per environment, {' / '.join(str(n) for n, _ in memory)} landers",
                    " / ".join(f"{r['env_kb']:.0f}" for _, r in memory) + " KiB",
                    "bare Box2D world: " + " / ".join(f"{r['floor_kb']:.0f}" for _, r in memory) + " KiB",
                    " / ".join(f"{r['env_kb'] / r['floor_kb']:.2f}" for _, r in memory), "", run])
    return out


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    context, rows = medians(sys.argv[1])
    load = context.get("load_avg") or [0.0]
    for cells in table_rows(rows, f"A, load {load[0]:.1f}"):
        print("| " + " | ".join(cells) + " |")
    print()
    print(f"{context.get('num_cpus')} CPUs at {context.get('mhz_per_cpu')} MHz, load average at "
          f"start {', '.join(f'{x:.1f}' for x in load)}; {context.get('date')}")


if __name__ == "__main__":
    main()
