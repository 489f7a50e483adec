"""Authentication under attack (issue 15): the public ``base.tsp`` while wrong tokens hammer
the admin API.

The collection of :mod:`bench.bench_serve` (one fitted relief, managed, an admin token set)
is served by ``tessera serve --production`` (gunicorn, 2 processes x 4 threads, the tarpit
worker). One ``wrk`` loads the public ``/bundles/relief/base.tsp`` (:data:`PUBLIC_THREADS`
= 2 threads, :data:`PUBLIC_CONNECTIONS` = 16 keep-alive connections, :data:`DURATION` s);
the attacker is a second ``wrk`` (:data:`ATTACK_THREADS` = 1 thread,
:data:`ATTACK_CONNECTIONS` = 32 keep-alive connections) sending ``GET /admin/api/objects``
with a wrong Bearer token: either a fresh random 32-character one on every request (a Lua
script, so no cache of refused tokens helps: only the per-address limiter, the bounded hash
pool and the tarpit do) or one fixed wrong token (as ``wrk -H`` would send). Both
generators run on the same loopback address as the server, on the same 2 cores.

Each of :data:`ROUNDS` rounds measures the public rate alone, beside the random-token attack
and beside the fixed-token attack, in an order that reverses from one round to the next
(alone, random, fixed; then fixed, random, alone; ...), so that a drift of the machine's
speed cancels over the rounds; each attacked figure is divided by its own round's unloaded
figure (the share, per pair), and the report gives the median of the shares and the
medians of the rates. Before the rounds, a first attack (the onset: each process spends its
free scrypt checks) is measured apart. Target: under attack the public route keeps >= 70 %
of its unloaded throughput. Needs ``wrk`` (``apt-get install -y wrk``); without it the
benchmark is skipped with that reason. Writes bench/results/auth.json.
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
ROUNDS = 7
#: the public load: wrk's threads and keep-alive connections
PUBLIC_THREADS = 2
PUBLIC_CONNECTIONS = 16
#: the attack: wrk's threads and keep-alive connections
ATTACK_THREADS = 1
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
    completed = subprocess.run(["wrk", f"-t{ATTACK_THREADS}", f"-c{ATTACK_CONNECTIONS}",
                                f"-d{int(duration)}s", "--timeout", "10s",
                                "-s", str(script), url], capture_output=True, text=True,
                               check=True)
    out["stdout"] = completed.stdout


def _alone(public: str, duration: float, server: int) -> dict:
    """``wrk`` on ``public``, with the server's CPU seconds during it."""
    cpu = _tree_cpu_s(server)
    result = _public_load(public, duration)
    return {**result, "server_cpu_s": round(_tree_cpu_s(server) - cpu, 3)}


def _public_load(public: str, duration: float) -> dict:
    return _wrk(public, duration, threads=PUBLIC_THREADS, connections=PUBLIC_CONNECTIONS)


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
    result = _public_load(public, duration)
    attacker.join()
    return result, {**_parse_attack(attack.get("stdout", "")),
                    "server_cpu_s": round(_tree_cpu_s(server) - cpu, 3)}


def _attack_alone(base: str, script: Path, duration: float, server: int) -> dict:
    """The attack with no public load: its rate and the server's CPU seconds meanwhile (what
    the refusals and the held connections cost the server, and nothing else)."""
    attack: dict = {}
    cpu = _tree_cpu_s(server)
    _attack(base + "/admin/api/objects", script, duration, attack)
    return {**_parse_attack(attack.get("stdout", "")),
            "server_cpu_s": round(_tree_cpu_s(server) - cpu, 3), "duration_s": duration}


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
            _public_load(public, 2.0)  # warm-up
            load_before = _load_average()
            # the onset: each process spends its FREE_FAILURES scrypt checks, then backs off
            onset, onset_attack = _attacked(public, base, script, DURATION, pid)
            rounds = []
            for index in range(ROUNDS):  # the order reverses each round: drift cancels
                phases = ["alone", "random", "fixed"]
                measured: dict = {}
                for phase in phases if index % 2 == 0 else phases[::-1]:
                    if phase == "alone":
                        measured["alone"] = _alone(public, DURATION, pid)
                    else:
                        measured[phase], measured[f"{phase}_attack"] = _attacked(
                            public, base, script if phase == "random" else fixed_script,
                            DURATION, pid)
                rounds.append(measured)
            attack_only = {phase: _attack_alone(base, script if phase == "random" else
                                                fixed_script, DURATION, pid)
                           for phase in ("random", "fixed")}
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
    return _report(rounds, onset, onset_attack, attack_only, after, load_before, load_after)


def _report(rounds: list[dict], onset: dict, onset_attack: dict, attack_only: dict,
            after: dict, load_before: list[float], load_after: list[float]) -> dict:
    """Print the table and write bench/results/auth.json (see the module docstring)."""
    alone = [r["alone"] for r in rounds]
    unloaded = statistics.median(a["rate"] for a in alone)
    summary: dict = {}
    for phase in ("random", "fixed"):
        shares = [r[phase]["rate"] / r["alone"]["rate"] for r in rounds]
        summary[phase] = {"rps_median": round(statistics.median(r[phase]["rate"]
                                                                for r in rounds), 1),
                          "shares": [round(x, 3) for x in shares],
                          "share_median": round(statistics.median(shares), 3),
                          "share_of_medians": round(statistics.median(
                              r[phase]["rate"] for r in rounds) / unloaded, 3),
                          "attack_rps": [r[f"{phase}_attack"]["rate"] for r in rounds]}
    rows = [(f"round {k + 1}", round(r["alone"]["rate"], 1), round(r["random"]["rate"], 1),
             f"{r['random']['rate'] / r['alone']['rate']:.0%}", round(r["fixed"]["rate"], 1),
             f"{r['fixed']['rate'] / r['alone']['rate']:.0%}",
             r["alone"]["errors"] + r["random"]["errors"] + r["fixed"]["errors"])
            for k, r in enumerate(rounds)]
    rows.append(("median", round(unloaded, 1), summary["random"]["rps_median"],
                 f"{summary['random']['share_median']:.0%}", summary["fixed"]["rps_median"],
                 f"{summary['fixed']['share_median']:.0%}", ""))
    rows.append(("onset (first attack)", "", round(onset["rate"], 1),
                 f"{onset['rate'] / unloaded:.0%}", "", "", onset["errors"]))
    print_table(f"public base.tsp req/s (wrk {PUBLIC_THREADS} threads x {PUBLIC_CONNECTIONS} "
                f"connections) alone and beside wrk {ATTACK_THREADS} thread x "
                f"{ATTACK_CONNECTIONS} connections of wrong tokens (gunicorn 2x4, "
                f"{DURATION:g} s each, {len(rounds)} rounds); share = attacked / the same "
                f"round's alone; target >= {TARGET_SHARE:.0%}",
                ["round", "alone", "random tokens", "share", "one fixed token", "share",
                 "errors"], rows)
    # the server's CPU: per public request (alone), and per refused request of an attack with
    # no public load (measured apart: beside ~4,000 public requests the ~150 refusals of a
    # held attack are lost in the noise of the public requests' cost)
    public_ms = statistics.median(1e3 * a["server_cpu_s"] / a["requests"] for a in alone)
    refusal = {phase: {"ms_per_refusal": round(1e3 * a["server_cpu_s"] / a["requests"], 3)
                       if a["requests"] else None,
                       "server_cpu_share_of_a_core": round(a["server_cpu_s"] / a["duration_s"],
                                                           3),
                       **a}
               for phase, a in attack_only.items()}
    print(f"server CPU: {public_ms:.2f} ms per public base.tsp; an attack alone "
          + "; ".join(f"({phase} tokens) {r['rate']:.0f} req/s, {r['ms_per_refusal']} ms per "
                      f"refusal, {r['server_cpu_share_of_a_core']:.1%} of a core"
                      for phase, r in refusal.items()))
    for phase in ("random", "fixed"):
        print(f"attack req/s, {phase} tokens (refused/sent): "
              + ", ".join(f"{r[phase + '_attack']['rate']:.0f} "
                          f"({r[phase + '_attack']['refused']}/"
                          f"{r[phase + '_attack']['requests']})" for r in rounds))
    print(f"onset attack: {onset_attack['rate']:.0f} req/s; load average {load_before} before, "
          f"{load_after} after")
    share = summary["random"]["share_median"]
    data = {"server": "gunicorn (tessera serve --production --processes 2 --threads 4, "
                      "tarpit worker)",
            "public_url": "/bundles/relief/base.tsp",
            "public_wrk": {"threads": PUBLIC_THREADS, "connections": PUBLIC_CONNECTIONS},
            "attack_wrk": {"threads": ATTACK_THREADS, "connections": ATTACK_CONNECTIONS},
            "duration_s": DURATION, "rounds": rounds, "onset": onset,
            "onset_attack": onset_attack, "order": "alone, random, fixed; reversed every "
                                                   "other round",
            "unloaded_rps_median": round(unloaded, 1),
            "random_token": summary["random"], "fixed_token": summary["fixed"],
            "server_cpu_ms_per_public_request": round(public_ms, 3),
            "attack_alone": refusal,
            "share_kept": share, "fixed_token_share": summary["fixed"]["share_median"],
            "onset_share": round(onset["rate"] / unloaded, 3),
            "target_share": TARGET_SHARE,
            "meets_target": min(share, summary["fixed"]["share_median"]) >= TARGET_SHARE,
            "right_token_from_the_attacked_address": after,
            "load_average_before": load_before, "load_average_after": load_after}
    write_results("auth", data)
    return data


if __name__ == "__main__":
    print(json.dumps(run(), indent=2))
