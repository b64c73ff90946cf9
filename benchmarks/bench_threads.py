"""10. Threads of the embedded server under load: prefill and decoding speed with 1 and 2 threads.

The embedded server's thread count (``ppprops.llm.embedded.default_threads``) is chosen when it
starts. This benchmark measures what each choice costs when other processes compete for the cores:
for ``--threads`` 1 and 2, with 0, 1 and 3 extra busy loops (processes spinning on a core, like a
``stress --cpu N``) started beside the server, it sends the same document-form prompt (CartPole,
about 700 tokens, prompt cache off) and asks for 48 tokens, and reads llama.cpp's own timings:
prompt tokens per second and generated tokens per second. The load average before each cell is
recorded too: the busy loops add to whatever else runs on the machine.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import statistics
import time
import urllib.request
from typing import Any

from _common import Context, Section, table

from ppprops.llm.embedded import EmbeddedServer, default_threads

THREADS = (1, 2)
BUSY = (0, 1, 3)
REPEATS = 2
ANSWER_TOKENS = 48


def _spin(stop: Any) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(100_000):
            x += 1


def _prompt() -> str:
    rows = []
    for k in range(10):
        vals = ",".join(f"{i}:{((k * 37 + i * 11) % 41 - 20) / 10:.2f}" for i in range(10))
        rows.append(f"return: {20.0 + 7 * k:.2f}\nparams: [{vals}]")
    return "# CartPole: linear policy search. Each entry below is one policy's return (higher is better) and its parameters, " \
           "from the lowest return to the highest.\n\n" + "\n\n".join(rows) + "\n\nreturn: 101.00\nparams: ["


def _ask(base_url: str, prompt: str, seed: int) -> dict[str, float]:
    root = base_url.removesuffix("/v1")
    body = {"prompt": prompt, "n_predict": ANSWER_TOKENS, "temperature": 1.0, "seed": seed, "cache_prompt": False,
            "ignore_eos": True}
    req = urllib.request.Request(root + "/completion", data=json.dumps(body).encode(), headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=600) as resp:
        t = json.loads(resp.read())["timings"]
    return {"prompt_tps": float(t["prompt_per_second"]), "gen_tps": float(t["predicted_per_second"]),
            "prompt_n": float(t["prompt_n"]), "gen_n": float(t["predicted_n"])}


def run(ctx: Context) -> Section:
    prompt = _prompt()
    repeats = 1 if ctx.quick else REPEATS
    rows, data = [], {}
    for threads in THREADS:
        with EmbeddedServer(context_size=4096, threads=threads) as server:
            _ask(server.base_url, prompt, 0)  # warm the weights into memory
            for busy in BUSY:
                stop = mp.Event()
                procs = [mp.Process(target=_spin, args=(stop,), daemon=True) for _ in range(busy)]
                for p in procs:
                    p.start()
                time.sleep(2.0)
                load = os.getloadavg()[0]
                try:
                    res = [_ask(server.base_url, prompt, 1 + r) for r in range(repeats)]
                finally:
                    stop.set()
                    for p in procs:
                        p.join(timeout=5)
                pt = statistics.median(r["prompt_tps"] for r in res)
                gt = statistics.median(r["gen_tps"] for r in res)
                data[f"t{threads}_busy{busy}"] = {"prompt_tps": pt, "gen_tps": gt, "load_before": load, "runs": res}
                rows.append([threads, busy, f"{load:.2f}", f"{pt:.0f}", f"{gt:.1f}"])
    body = [
        f"The same CartPole document ({int(data['t1_busy0']['runs'][0]['prompt_n'])} prompt tokens, cache off) and "
        f"{ANSWER_TOKENS} generated tokens per request, {repeats} request(s) per cell (median); llama.cpp's own timings. "
        "Extra busy loops run beside the server; the load average is read just before each cell (it includes every other "
        "process on the machine, and lags).",
        "",
        table(["threads", "extra busy loops", "load average before", "prefill tokens/s", "decoding tokens/s"], rows),
        "",
        f"- `default_threads` on {os.cpu_count()} cores now: {default_threads()} (load {os.getloadavg()[0]:.2f}).",
    ]
    return Section("threads", "10. Embedded server threads under load", "\n".join(body), data)
