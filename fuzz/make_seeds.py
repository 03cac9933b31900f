#!/usr/bin/env python3
"""Writes the seed corpora of the fuzzers into fuzz/corpus/{core,service}/.

Service inputs are framed operations ([kind][u16 length][proto bytes], see
fuzz/harness.h) whose protos are encoded from text format by protoc, so the
seeds stay readable here. Core inputs follow RunCoreInput's byte layout.
Run from anywhere: python3 fuzz/make_seeds.py
"""
import pathlib
import re
import struct
import subprocess

ROOT = pathlib.Path(__file__).resolve().parent.parent
PROTO = "mll/v1/multi_lunar_lander.proto"


def methods():
    """mll::service::Method's enumerators in order (the harness's operation kinds)."""
    header = (ROOT / "server/service/include/mll/service/metrics.h").read_text()
    body = re.search(r"enum class Method \{(.*?)\};", header, re.S).group(1)
    return re.findall(r"^\s*k(\w+),", body, re.M)


KINDS = methods()


def encode(kind, text):
    return subprocess.run(
        ["protoc", f"--encode=mll.v1.{kind}Request", "-I", str(ROOT / "proto"),
         PROTO], input=text.encode(), capture_output=True, check=True).stdout


def op(kind, text=""):
    body = encode(kind, text)
    return bytes([KINDS.index(kind)]) + struct.pack("<H", len(body)) + body


def int32s(values, shape=None):
    data = "".join(f"\\{b:03o}" for b in struct.pack(f"<{len(values)}i", *values))
    dims = " ".join(f"shape: {d}" for d in (shape or [len(values)]))
    return f'dtype: DTYPE_INT32 {dims} data: "{data}"'


def float_pairs(values):
    data = "".join(f"\\{b:03o}" for b in struct.pack(f"<{len(values)}f", *values))
    return f'dtype: DTYPE_FLOAT32 shape: {len(values) // 2} shape: 2 data: "{data}"'


def service_seeds():
    discrete = op("CreateEnv", "config { n_landers: 3 }")
    yield "parallel_episode", discrete + op("ResetEnv", 'name: "@0" seed: 7') + b"".join(
        op("StepEnv", f'name: "@0" actions {{ {int32s([i % 4, 2, (i + 1) % 4])} }}')
        for i in range(40))
    yield "aec_episode", discrete + op("ResetEnv", 'name: "@0" seed: 1') + b"".join(
        op("StepAgent", f'name: "@0" action {{ discrete: {i % 4} }}') for i in range(30)) + op(
        "StepAgent", 'name: "@0"') + op("StepAgent", 'name: "@0" agent: 2 action { discrete: 1 }')
    yield "continuous_render", op(
        "CreateEnv", "config { n_landers: 2 continuous: true render_mode: RENDER_MODE_RGB_ARRAY }"
    ) + op("RenderEnv", 'name: "@0"') + op("ResetEnv", 'name: "@0"') + op(
        "StepEnv", f'name: "@0" actions {{ {float_pairs([1.0, 0.5, -1.0, float("nan")])} }}') + op(
        "StepEnv", f'name: "@0" actions {{ {float_pairs([1.0, 0.5, -1.0, 0.9])} }}') + op(
        "RenderEnv", 'name: "@0" format: FRAME_FORMAT_PNG') + op(
        "StepAgent", 'name: "@0" action { continuous { dtype: DTYPE_FLOAT32 shape: 2 data: "\\000\\000\\200\\177\\000\\000\\000\\000" } }')
    yield "batch_and_list", discrete + op("CreateEnv", "config { n_landers: 1 max_cycles: 3 } ") + op(
        "CreateEnv", "config { auto_reset: true n_landers: 32 }") + op(
        "ResetEnv", 'name: "@0"') + op("ResetEnv", 'name: "@1"') + op("ResetEnv", 'name: "@2"') + b"".join(
        op("StepBatch", f'steps {{ name: "@0" actions {{ {int32s([2, 2, 2])} }} }} '
                        f'steps {{ name: "@1" actions {{ {int32s([0])} }} }} '
                        f'steps {{ name: "@2" actions {{ {int32s([1] * 32)} }} }}')
        for _ in range(5)) + op("ListEnvs", "page_size: 2") + op("GetEnv", 'name: "@1"') + op(
        "DeleteEnv", 'name: "@1"') + op("StepEnv", f'name: "@1" actions {{ {int32s([0])} }}') + op(
        "KeepAlive", 'names: "@0" names: "@1" names: "@2" names: "envs/none" names: "bad"')
    yield "bad_requests", op("CreateEnv", "config { n_landers: 33 gravity: 0 }") + discrete + op(
        "StepEnv", f'name: "@0" actions {{ {int32s([1, 1, 1])} }}') + op(
        "ResetEnv", 'name: "@0"') + op("StepEnv", 'name: "@0" actions { dtype: DTYPE_INT32 shape: 3 data: "\\001" }') + op(
        "StepEnv", f'name: "@0" actions {{ {int32s([7, -1, 1 << 30])} }}') + op(
        "GetEnv", 'name: "envs/0123456789abcdef0123456789abcdef"') + op("GetEnv", 'name: "nonsense"') + op(
        "StepBatch", 'steps { name: "@0" } steps { name: "@0" }') + op("ListEnvs", 'page_token: "zz"') + op(
        "RenderEnv", 'name: "@0" format: 9')
    # Session operations (the first env bound to the session, the second
    # detached) and packed batches, one of them with a mismatched env.
    yield "session_and_packed", op(
        "Session", "sequence: 1 create_env { config { n_landers: 2 } }") + op(
        "Session", "sequence: 2 create_env { detached: true config { n_landers: 2 } }") + op(
        "CreateEnv", "config { n_landers: 3 }") + b"".join(
        op("Session", f'sequence: {3 + i} reset_env {{ name: "@{i}" seed: {i} }}') for i in range(3)) + b"".join(
        op("Session", f'step_batch {{ packed {{ names: "@0" names: "@1" '
                      f'actions {{ {int32s([i % 4, 2, 1, (i + 3) % 4], [2, 2])} }} }} }}')
        for i in range(6)) + op(
        "StepBatch", f'packed {{ names: "@0" names: "@2" actions {{ {int32s([1, 2, 3, 0], [2, 2])} }} }}') + op(
        "Session", f'step_env {{ name: "@1" actions {{ {int32s([3, 3])} }} }}') + op(
        "Session", 'step_agent { name: "@0" action { discrete: 2 } }') + op(
        "Session", 'render_env { name: "@0" }') + op("Session", 'get_env { name: "@1" }') + op(
        "Session", 'delete_env { name: "@0" }') + op("Session", "sequence: 99")


def core_seeds():
    defaults = bytes(6)  # The six real-valued fields at their defaults.

    def config(landers, flags, cycles):
        return bytes([landers, flags, cycles]) + defaults

    reset = bytes([0, 1]) + struct.pack("<Q", 42)
    yield "discrete_parallel", config(3, 0b11100, 200) + reset + b"".join(
        bytes([2, i % 4, 2, (i * 7) % 4]) for i in range(150))
    yield "continuous_aec_render", config(2, 0b100011, 120) + reset + b"".join(
        bytes([10, 0, 200, 150]) for _ in range(80)) + bytes([1, 10, 255]) + bytes([1])
    yield "many_landers_wind", config(32, 0b00010, 60) + bytes([0, 0]) + b"".join(
        bytes([3]) + bytes([(i + k) % 4 for k in range(32)]) for i in range(70))
    yield "nan_actions", config(1, 0b1, 50) + reset + bytes([4, 230]) + struct.pack(
        "<f", float("nan")) + bytes([100]) + bytes([4, 100, 240]) + struct.pack("<f", float("inf"))
    yield "bad_config", bytes([33, 0, 0, 3]) + struct.pack("<d", 1.0) + bytes(5)


def main():
    for name, seeds in (("service", service_seeds()), ("core", core_seeds())):
        directory = ROOT / "fuzz" / "corpus" / name
        directory.mkdir(parents=True, exist_ok=True)
        for stem, data in seeds:
            (directory / stem).write_bytes(data)
            print(f"{directory / stem}: {len(data)} bytes")


if __name__ == "__main__":
    main()
