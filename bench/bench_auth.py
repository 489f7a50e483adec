"""Authentication under attack (issue 15): the public ``base.tsp`` while wrong tokens hammer
the admin API.

The collection of :mod:`bench.bench_serve` (one fitted relief, managed, an admin token set)
is served by ``tessera serve --production`` (gunicorn, 2 processes x 4 threads). ``wrk``
loads the public ``/bundles/relief/base.tsp`` (2 threads, 16 keep-alive connections, 5 s)
twice: alone, then while a second ``wrk`` (1 thread, 32 connections) sends
``GET /admin/api/objects`` with a fresh random 32-character Bearer token on every request
(a Lua script), so that no cache of refused tokens helps: only the per-address limiter and
the bounded hash pool of :mod:`fitter.server.admin.auth` do. Both generators run on the
same loopback address as the server, on the same 2 cores. Target: under attack the public
route keeps >= 70 % of its unloaded throughput. Needs ``wrk`` (``apt-get install -y wrk``);
without it the benchmark is skipped with that reason. Writes bench/results/auth.json.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

from bench import print_table, write_results
from bench.bench_serve import TOKEN, _make_collection, _wrk, production_server

DURATION = 4.0  # seconds of public load, each phase
ROUNDS = 3
ATTACK_CONNECTIONS = 32
TARGET_SHARE = 0.70

#: wrk's Lua hook: a new random Bearer token (URL-safe base64 alphabet, 32 characters) on
#: every request, so each one is a fresh guess
ATTACK_SCRIPT = """
math.randomseed(os.time())
local alphabet = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_"
request = function()
  local token = {}
  for i = 1, 32 do
    local k = math.random(1, #alphabet)
    token[i] = alphabet:sub(k, k)
  end
  wrk.headers["Authorization"] = "Bearer " .. table.concat(token)
  return wrk.format("GET")
end
"""


#: the other attack: one fixed wrong token, as a plain ``wrk -H`` would send
FIXED_SCRIPT = """
wrk.headers["Authorization"] = "Bearer not-the-admin-token-0123456789"
"""


def _attack(url: str, script: Path, duration: float, out: dict) -> None:
    completed = subprocess.run(["wrk", "-t1", f"-c{ATTACK_CONNECTIONS}", f"-d{int(duration)}s",
                                "-s", str(script), url], capture_output=True, text=True,
                               check=True)
    out["stdout"] = completed.stdout


def _alone(public: str, duration: float, server: int) -> dict:
    """``wrk`` on ``public``, with the server's CPU seconds during it."""
    cpu = _tree_cpu_s(server)
    result = _wrk(public, duration)
    return {**result, "server_cpu_s": round(_tree_cpu_s(server) - cpu, 3)}


def _attacked(public: str, base: str, script: Path, duration: float,
              server: int) -> tuple[dict, dict]:
    """``wrk`` on ``public`` while the attack runs (started 0.5 s before, ended after), and
    the server's CPU seconds over the whole attack."""
    attack: dict = {}
    attacker = threading.Thread(target=_attack, args=(base + "/admin/api/objects", script,
                                                      duration + 1.5, attack))
    cpu = _tree_cpu_s(server)
    attacker.start()
    time.sleep(0.5)
    result = _wrk(public, duration)
    attacker.join()
    return result, {**_parse_attack(attack.get("stdout", "")),
                    "server_cpu_s": round(_tree_cpu_s(server) - cpu, 3)}


def _parse_attack(text: str) -> dict:
    import re

    rate = re.search(r"Requests/sec:\s+([\d.]+)", text)
    total = re.search(r"(\d+) requests in", text)
    non2xx = re.search(r"Non-2xx or 3xx responses:\s+(\d+)", text)
    return {"rate": float(rate.group(1)) if rate else None,
            "requests": int(total.group(1)) if total else None,
            "refused": int(non2xx.group(1)) if non2xx else 0}


def _tree_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` and its descendants (the
    gunicorn arbiter, its workers, the job runner), from ``/proc``."""
    total, todo = 0.0, [pid]
    tick = os.sysconf("SC_CLK_TCK")
    while todo:
        current = todo.pop()
        try:
            fields = Path(f"/proc/{current}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
            for task in Path(f"/proc/{current}/task").iterdir():
                todo.extend(int(c) for c in (task / "children").read_text().split())
        except (FileNotFoundError, ProcessLookupError):
            continue  # gone meanwhile
    return total


def _load_average() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


def run() -> dict | None:
    if shutil.which("wrk") is None:
        print("auth benchmark skipped: wrk is not on PATH (apt-get install -y wrk); a Python "
              "load generator on the same 2 cores could not tell the server's share apart")
        return None
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "collection"
        object_id = _make_collection(root)
        script = Path(tmp) / "attack.lua"
        script.write_text(ATTACK_SCRIPT)
        fixed_script = Path(tmp) / "fixed.lua"
        fixed_script.write_text(FIXED_SCRIPT)
        with production_server(root, Path(tmp) / "serve.log") as (base, pid):
            public = f"{base}/bundles/{object_id}/base.tsp"
            _wrk(public, 2.0)  # warm-up
            load_before = _load_average()
            # the onset: each process spends its FREE_FAILURES scrypt checks, then backs off
            onset, first_attack = _attacked(public, base, script, DURATION, pid)
            attacks = [first_attack]
            alone, attacked, fixed, fixed_attacks = [], [], [], []
            for _ in range(ROUNDS):  # alternated: other work on the machine varies
                alone.append(_alone(public, DURATION, pid))
                result, attack = _attacked(public, base, script, DURATION, pid)
                attacked.append(result)
                attacks.append(attack)
                result, attack = _attacked(public, base, fixed_script, DURATION, pid)
                fixed.append(result)
                fixed_attacks.append(attack)
            load_after = _load_average()
            # the right token from the attacked address: refused until its backoff ends
            try:
                after = {"status": urllib.request.urlopen(urllib.request.Request(
                    base + "/admin/api/objects", headers={"Authorization": f"Bearer {TOKEN}"}),
                    timeout=10).status}
            except urllib.error.HTTPError as exc:
                after = {"status": exc.code, "retry_after": exc.headers.get("Retry-After")}
            except (TimeoutError, urllib.error.URLError) as exc:
                after = {"status": None, "error": str(exc)}
    unloaded = statistics.median(r["rate"] for r in alone)
    loaded = statistics.median(r["rate"] for r in attacked)
    share = loaded / unloaded
    fixed_rate = statistics.median(r["rate"] for r in fixed)
    rows = [(f"round {k + 1}", round(a["rate"], 1), round(b["rate"], 1),
             f"{b['rate'] / a['rate']:.0%}", round(c["rate"], 1), f"{c['rate'] / a['rate']:.0%}",
             a["errors"] + b["errors"] + c["errors"])
            for k, (a, b, c) in enumerate(zip(alone, attacked, fixed, strict=True))]
    rows.append(("median", round(unloaded, 1), round(loaded, 1), f"{share:.0%}",
                 round(fixed_rate, 1), f"{fixed_rate / unloaded:.0%}", ""))
    rows.append(("onset (first attack)", "", round(onset["rate"], 1),
                 f"{onset['rate'] / unloaded:.0%}", "", "", onset["errors"]))
    print_table(f"public base.tsp req/s (16 connections) alone and beside {ATTACK_CONNECTIONS} "
                f"connections of wrong tokens (gunicorn 2x4, wrk, {DURATION:g} s each); target "
                f">= {TARGET_SHARE:.0%}",
                ["round", "alone", "random tokens", "share", "one fixed token", "share",
                 "errors"], rows)
    # the server's CPU per request: a public one (alone), then an attack's refusal (the
    # attack phase's CPU less its public requests at that cost); robust to other work on
    # the machine, which moves the req/s figures far more
    public_ms = statistics.median(1e3 * a["server_cpu_s"] / a["requests"] for a in alone)

    def refusal_ms(runs: list[dict], publics: list[dict]) -> float:
        costs = [1e3 * (a["server_cpu_s"] - p["requests"] * public_ms / 1e3) / a["requests"]
                 for a, p in zip(runs, publics, strict=True) if a["requests"]]
        return statistics.median(costs)

    random_ms = refusal_ms(attacks[1:], attacked)
    fixed_ms = refusal_ms(fixed_attacks, fixed)
    print(f"server CPU per request: public base.tsp {public_ms:.2f} ms; refused wrong token "
          f"{random_ms:.2f} ms (random tokens, scrypt probes included), {fixed_ms:.2f} ms "
          "(one fixed token)")
    for name, runs in (("random", attacks), ("fixed", fixed_attacks)):
        print(f"attack req/s, {name} tokens (refused/sent): "
              + ", ".join(f"{a['rate']:.0f} ({a['refused']}/{a['requests']})" for a in runs))
    data = {"server": "gunicorn (tessera serve --production --processes 2 --threads 4)",
            "public_url": "/bundles/relief/base.tsp", "public_connections": 16,
            "attack_connections": ATTACK_CONNECTIONS, "duration_s": DURATION,
            "rounds": ROUNDS, "alone": alone, "attacked": attacked, "onset": onset,
            "attacks": attacks, "fixed_token": fixed, "fixed_token_attacks": fixed_attacks,
            "fixed_token_rps_median": round(fixed_rate, 1),
            "fixed_token_share": round(fixed_rate / unloaded, 3),
            "unloaded_rps_median": round(unloaded, 1),
            "server_cpu_ms_per_public_request": round(public_ms, 3),
            "server_cpu_ms_per_refused_random_token": round(random_ms, 3),
            "server_cpu_ms_per_refused_fixed_token": round(fixed_ms, 3),
            "attacked_rps_median": round(loaded, 1), "share_kept": round(share, 3),
            "onset_share": round(onset["rate"] / unloaded, 3),
            "target_share": TARGET_SHARE, "meets_target": share >= TARGET_SHARE,
            "right_token_from_the_attacked_address": after,
            "load_average_before": load_before, "load_average_after": load_after}
    write_results("auth", data)
    return data


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
