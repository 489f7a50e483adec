"""The admin gate under attack and under change (issue 15, part H3): wrong tokens are
rate-limited per client address with exponential backoff, refused cheaply before the
costly hash, and hashed on a bounded pool; the public routes keep answering during an
attack; ``tessera admin set-token`` and ``POST /admin/logout`` take effect at once on a
running app."""

from __future__ import annotations

import io
import secrets
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from conftest import ADMIN_TOKEN
from live import LiveServer

from fitter.cli import main
from fitter.collection.catalog import Catalog
from fitter.collection.tokens import MAX_TOKEN_LENGTH, check_token_strength
from fitter.server.admin import auth
from fitter.server.admin.auth import FREE_FAILURES, HASH_POOL_SIZE, FailureLimiter

#: wall-clock bounds below: `make test` runs this file alone, after the parallel part
pytestmark = pytest.mark.timing

OBJECTS = "/admin/api/objects"


class FakeClock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class CountingHash:
    """A stand-in for ``check_password_hash`` (``real(token_hash, presented)``, a cheap
    comparison) that counts calls and the most running at once, and takes ``seconds`` per
    call like scrypt."""

    def __init__(self, real, seconds: float = 0.05) -> None:
        self.real, self.seconds = real, seconds
        self.calls = self.running = self.most_at_once = 0
        self._lock = threading.Lock()

    def __call__(self, token_hash: str, presented: str) -> bool:
        with self._lock:
            self.calls += 1
            self.running += 1
            self.most_at_once = max(self.most_at_once, self.running)
        try:
            time.sleep(self.seconds)
            return self.real(token_hash, presented)
        finally:
            with self._lock:
                self.running -= 1


@pytest.fixture()
def counting_hash(monkeypatch):
    counter = CountingHash(lambda token_hash, presented: presented == ADMIN_TOKEN)
    monkeypatch.setattr(auth, "check_password_hash", counter)
    return counter


@pytest.fixture()
def clock(admin_app):
    fake = FakeClock()
    admin_app.extensions["tessera_admin"].limiter = FailureLimiter(clock=fake)
    return fake


@pytest.fixture()
def admin_app(admin_app_factory):
    return admin_app_factory()


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def wrong_token() -> str:
    return "wrong-" + secrets.token_urlsafe(24)


def from_address(app, address: str):
    client = app.test_client()
    client.environ_base["REMOTE_ADDR"] = address
    return client


def assert_admin_api_headers(client, response) -> None:
    """``response`` (answered before Flask) carries the headers Flask's hooks put on an admin
    API answer (the security headers, ``Cache-Control: no-store`` ...)."""
    reference = client.get(OBJECTS)  # no token: a 401 made by the Flask view
    assert reference.status_code == 401
    own = {"content-length", "content-type", "www-authenticate", "retry-after", "set-cookie",
           "vary"}
    for name, value in reference.headers.items():
        if name.lower() not in own:
            assert response.headers.get(name) == value, name


# ------------------------------------------------------------------------- the limiter
def test_the_limiter_backs_off_exponentially_up_to_its_cap_and_forgets():
    clock = FakeClock()
    limiter = FailureLimiter(free_failures=3, base_delay=1.0, max_delay=8.0,
                             forget_after=100.0, max_addresses=2, clock=clock)
    waits = [limiter.record_failure("a") for _ in range(8)]
    assert waits == [0, 0, 1, 2, 4, 8, 8, 8]
    assert limiter.wait("a") == 8 and limiter.wait("b") == 0
    clock.now += 8.5
    assert limiter.wait("a") == 0
    assert limiter.record_failure("a") == 8  # still counted: the next failure waits the cap
    clock.now += 101
    assert limiter.wait("a") == 0 and limiter.record_failure("a") == 0  # forgotten
    limiter.record_success("a")
    for address in ("b", "c", "d"):  # at most two addresses are followed
        for _ in range(5):
            limiter.record_failure(address)
    assert limiter.wait("b") == 0 and limiter.wait("d") > 0
    with pytest.raises(ValueError, match="free_failures must be >= 0, got -1"):
        FailureLimiter(free_failures=-1)
    with pytest.raises(ValueError, match="need 0 < base_delay <= max_delay, got 5.0, 1.0"):
        FailureLimiter(base_delay=5.0, max_delay=1.0)
    with pytest.raises(ValueError, match="max_addresses must be >= 1, got 0"):
        FailureLimiter(max_addresses=0)


def test_a_burst_of_wrong_tokens_gets_429_and_the_hash_runs_on_a_bounded_pool(
        admin_app, counting_hash, clock):
    statuses: list[int] = []
    lock = threading.Lock()

    def attacker() -> None:
        client = from_address(admin_app, "10.0.0.1")
        for _ in range(4):
            status = client.get(OBJECTS, headers=bearer(wrong_token())).status_code
            with lock:
                statuses.append(status)

    threads = [threading.Thread(target=attacker) for _ in range(12)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert len(statuses) == 48
    assert counting_hash.most_at_once <= HASH_POOL_SIZE
    assert counting_hash.calls <= FREE_FAILURES  # the clock stands still: no wait expires
    assert statuses.count(401) == counting_hash.calls
    assert set(statuses) <= {401, 429, 503} and 429 in statuses  # one hash per address
    client = from_address(admin_app, "10.0.0.1")
    while counting_hash.calls < FREE_FAILURES:  # spend the free failures one at a time
        assert client.get(OBJECTS, headers=bearer(wrong_token())).status_code == 401
    # then the address gets 429 with Retry-After, in JSON, without hashing
    calls = counting_hash.calls
    response = client.get(OBJECTS, headers=bearer(wrong_token()))
    assert response.status_code == 429
    assert int(response.headers["Retry-After"]) >= 1
    assert response.get_json()["retry_after"] == int(response.headers["Retry-After"])
    assert "too many admin token attempts" in response.get_json()["error"]
    assert_admin_api_headers(client, response)
    assert from_address(admin_app, "10.0.0.1").get(
        OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 429  # even the right one waits
    assert counting_hash.calls == calls
    # another address is not blocked
    other = from_address(admin_app, "10.0.0.2")
    assert other.get(OBJECTS, headers=bearer(wrong_token())).status_code == 401
    assert other.get(OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 200
    # after the backoff the right token works, and it clears the address's record
    clock.now += int(response.headers["Retry-After"]) + 0.1
    assert client.get(OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 200
    assert client.get(OBJECTS, headers=bearer(wrong_token())).status_code == 401


def test_the_backoff_doubles_with_each_failure_after_the_free_ones(admin_app, counting_hash,
                                                                   clock):
    client = from_address(admin_app, "10.0.0.3")
    for _ in range(FREE_FAILURES):
        assert client.get(OBJECTS, headers=bearer(wrong_token())).status_code == 401
    waits = []
    for _ in range(3):
        response = client.get(OBJECTS, headers=bearer(wrong_token()))
        assert response.status_code == 429
        waits.append(int(response.headers["Retry-After"]))
        clock.now += waits[-1] + 0.01
        assert client.get(OBJECTS, headers=bearer(wrong_token())).status_code == 401
    assert waits == [1, 2, 4]
    assert counting_hash.calls == FREE_FAILURES + 3


def test_tokens_of_impossible_shape_and_repeated_ones_are_refused_without_hashing(
        admin_app, counting_hash, clock):
    client = from_address(admin_app, "10.0.0.4")
    for token in ("short", "x" * (MAX_TOKEN_LENGTH + 1), "é" * 20, "tab\tinside-a-token"):
        assert client.get(OBJECTS, headers=bearer(token)).status_code == 401, token
    assert counting_hash.calls == 0
    repeated = wrong_token()
    for _ in range(3 * FREE_FAILURES):  # a repeated refused token is no new guess
        response = client.get(OBJECTS, headers=bearer(repeated))
        assert response.status_code == 401
    assert counting_hash.calls == 1
    assert response.get_json() == {"error": "wrong admin token"}
    assert response.headers["WWW-Authenticate"].startswith("Bearer")
    assert_admin_api_headers(client, response)
    assert client.get(OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 200
    assert client.get(OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 200
    assert counting_hash.calls == 2  # the right token is hashed once, then remembered


def test_the_secret_must_be_printable_ascii_of_bounded_length():
    with pytest.raises(ValueError, match="at most 256 characters long, got 257"):
        check_token_strength("x" * 257)
    with pytest.raises(ValueError, match=r"printable ASCII characters only .*got 'é'"):
        check_token_strength("é" * 20)
    with pytest.raises(ValueError, match="at least 16 characters long, got 5"):
        check_token_strength("short")


def test_the_hash_pool_refuses_with_503_when_its_queue_is_full(admin_app, monkeypatch):
    slow = CountingHash(lambda token_hash, presented: False, seconds=0.8)
    monkeypatch.setattr(auth, "check_password_hash", slow)
    monkeypatch.setattr(auth, "HASH_WAIT_S", 0.3)
    statuses: list[int] = []

    def attempt(index: int) -> None:
        client = from_address(admin_app, f"10.1.0.{index}")  # many addresses: no limiter
        statuses.append(client.get(OBJECTS, headers=bearer(wrong_token())).status_code)

    threads = [threading.Thread(target=attempt, args=(i,)) for i in range(6)]
    start = time.monotonic()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(10)
    assert slow.most_at_once == HASH_POOL_SIZE
    assert statuses.count(503) >= 4 and statuses.count(401) >= 1
    assert time.monotonic() - start < 2.0  # the excess is refused, never queued behind
    response = from_address(admin_app, "10.1.1.1").get(OBJECTS, headers=bearer("x" * 20))
    assert response.status_code in (401, 503)


def test_the_login_page_shows_the_wait(admin_app, counting_hash, clock):
    from test_admin import csrf_of

    client = from_address(admin_app, "10.0.0.5")
    for _ in range(FREE_FAILURES):
        response = client.post("/admin/login", data={"token": wrong_token(),
                                                     "csrf_token": csrf_of(client)})
        assert response.status_code == 401
    response = client.post("/admin/login", data={"token": ADMIN_TOKEN,
                                                 "csrf_token": csrf_of(client)})
    assert response.status_code == 429 and response.headers["Retry-After"] == "1"
    assert "try again in 1 s" in response.get_data(as_text=True)
    clock.now += 1.5
    response = client.post("/admin/login", data={"token": ADMIN_TOKEN,
                                                 "csrf_token": csrf_of(client)})
    assert response.status_code == 302


def test_public_routes_answer_while_wrong_tokens_hammer_the_admin(admin_app):
    """Real scrypt checks: 8 threads send fresh wrong tokens as fast as they can; a public
    request must still complete quickly."""
    stop = threading.Event()
    attempts = [0]

    with LiveServer(admin_app) as live:
        def attacker() -> None:
            while not stop.is_set():
                request = urllib.request.Request(live.url + OBJECTS,
                                                 headers=bearer(wrong_token()))
                try:
                    urllib.request.urlopen(request, timeout=10).read()
                except urllib.error.HTTPError as exc:
                    assert exc.code in (401, 429, 503)
                attempts[0] += 1

        threads = [threading.Thread(target=attacker, daemon=True) for _ in range(8)]
        for thread in threads:
            thread.start()
        try:
            time.sleep(0.5)
            worst = 0.0
            for _ in range(10):
                start = time.perf_counter()
                with urllib.request.urlopen(live.url + "/api/objects", timeout=10) as response:
                    assert response.status == 200
                worst = max(worst, time.perf_counter() - start)
        finally:
            stop.set()
            for thread in threads:
                thread.join(15)
    assert worst < 0.5, f"a public request took {worst:.2f} s during the attack"
    assert attempts[0] > 10


# ---------------------------------------------------------- rotation and logout at once
def set_token(monkeypatch, collection: Path, token: str) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO(token + "\n"))
    assert main(["admin", "set-token", str(collection)]) == 0


def test_set_token_applies_to_the_running_app_at_once(tmp_path, monkeypatch, admin_app_factory):
    from test_admin import login

    collection = tmp_path / "collection"
    collection.mkdir()
    old, new = "the-old-admin-token-0123", "the-new-admin-token-4567"
    set_token(monkeypatch, collection, old)
    app = admin_app_factory(collection, TESSERA_ADMIN_TOKEN="")
    client = app.test_client()
    assert client.get(OBJECTS, headers=bearer(old)).status_code == 200
    browser = app.test_client()
    assert login(browser, old).status_code == 302
    assert browser.get("/admin/").status_code == 200
    assert client.get(OBJECTS, headers=bearer(new)).status_code == 401  # remembered as wrong
    set_token(monkeypatch, collection, new)
    assert client.get(OBJECTS, headers=bearer(old)).status_code == 401
    assert client.get(OBJECTS, headers=bearer(new)).status_code == 200
    assert browser.get("/admin/").status_code == 302  # a session of the old secret is void
    assert browser.get(OBJECTS).status_code == 401
    assert login(browser, new).status_code == 302


def test_the_environment_token_keeps_precedence_over_set_token(tmp_path, monkeypatch,
                                                               admin_app_factory):
    app = admin_app_factory()
    collection = Path(app.config["TESSERA_COLLECTION"])
    client = app.test_client()
    catalog_token = "a-catalog-admin-token-0123"
    set_token(monkeypatch, collection, catalog_token)
    assert client.get(OBJECTS, headers=bearer(ADMIN_TOKEN)).status_code == 200
    assert client.get(OBJECTS, headers=bearer(catalog_token)).status_code == 401


def test_logout_revokes_the_cookie_and_a_replayed_copy(admin_app):
    from test_admin import csrf_of, login

    collection = admin_app.config["TESSERA_COLLECTION"]
    with Catalog(collection) as catalog:
        with catalog.transaction() as conn:
            catalog.add_object("vase", "Vase", published=True, bundle_path="vase", conn=conn)
    browser = admin_app.test_client()
    assert login(browser).status_code == 302
    cookie = browser.get_cookie("tessera_admin").value
    csrf = csrf_of(browser, "/admin/")
    thief = admin_app.test_client()
    thief.set_cookie("tessera_admin", cookie)
    assert thief.get("/admin/").status_code == 200  # the copy works while the session lives
    assert browser.post("/admin/logout", data={"csrf_token": csrf}).status_code == 302
    assert thief.get("/admin/").status_code == 302
    response = thief.post("/admin/objects/vase/unpublish", data={"csrf_token": csrf})
    assert response.status_code == 302 and response.headers["Location"].startswith(
        "/admin/login")
    assert thief.patch("/admin/api/objects/vase", headers={"X-CSRF-Token": csrf},
                       json={"published": False}).status_code == 401
    with Catalog(collection) as catalog:
        assert catalog.get_object("vase")["published"] == 1
    # a new login works, and a logout elsewhere ends it too (one secret, one admin)
    assert login(browser).status_code == 302
    other = admin_app.test_client()
    assert login(other).status_code == 302
    other.post("/admin/logout", data={"csrf_token": csrf_of(other, "/admin/")})
    assert browser.get("/admin/").status_code == 302


# ------------------------------------------------------------------------- the tarpit
def test_hold_connection_marks_only_a_gunicorn_socket_and_is_taken_once():
    from fitter.server import tarpit

    sock = object()
    tarpit.hold_connection({})  # no socket (development server, test client): nothing
    tarpit.hold_connection({tarpit.SOCKET_ENVIRON_KEY: sock}, 0.5)
    tarpit.hold_connection({tarpit.SOCKET_ENVIRON_KEY: sock}, 0.25)  # the longer one holds
    assert tarpit.take_hold(sock) == 0.5
    assert tarpit.take_hold(sock) == 0.0  # taken: a later socket of the same id starts clean
    for bad in (0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="seconds must be a positive finite number"):
            tarpit.hold_connection({tarpit.SOCKET_ENVIRON_KEY: sock}, bad)


class _Conn:
    def __init__(self) -> None:
        self.sock = object()


def _finished(keepalive: object):
    from concurrent import futures

    done = futures.Future()
    done.set_result(keepalive)
    return done


@pytest.fixture()
def tarpit_worker(monkeypatch, tmp_path):
    """A :class:`TarpitThreadWorker` outside gunicorn's arbiter, with gunicorn's own
    ``finish_request`` replaced by a recorder of ``(connection, kept alive)``."""
    import logging

    from gunicorn.config import Config
    from gunicorn.workers.gthread import ThreadWorker

    from fitter.server.tarpit_worker import TarpitThreadWorker

    handed: list[tuple[object, object]] = []
    monkeypatch.setattr(ThreadWorker, "finish_request",
                        lambda self, conn, fs: handed.append((conn, fs.result())))
    worker = TarpitThreadWorker(0, 0, [], None, 30, Config(), logging.getLogger("test"))
    worker.handed = handed
    return worker


def test_the_worker_holds_a_marked_kept_alive_connection_until_its_time(tarpit_worker,
                                                                        monkeypatch):
    from fitter.server import tarpit
    from fitter.server import tarpit_worker as worker_module

    worker = tarpit_worker
    plain, marked, closing = _Conn(), _Conn(), _Conn()
    worker.finish_request(plain, _finished(True))
    assert worker.handed == [(plain, True)]  # not marked: back to gunicorn at once
    for conn in (marked, closing):
        tarpit.hold_connection({tarpit.SOCKET_ENVIRON_KEY: conn.sock}, 0.2)
    worker.finish_request(closing, _finished(False))  # gunicorn closes it: nothing to hold
    worker.finish_request(marked, _finished(True))
    assert worker.handed[1:] == [(closing, False)] and len(worker.held) == 1
    worker.release_due()
    assert len(worker.handed) == 2  # not yet
    time.sleep(0.25)
    worker.release_due()
    assert worker.handed[2:] == [(marked, True)] and not worker.held
    # beyond MAX_HELD_CONNECTIONS a marked connection is closed instead of held
    monkeypatch.setattr(worker_module, "MAX_HELD_CONNECTIONS", 1)
    first, second = _Conn(), _Conn()
    for conn in (first, second):
        tarpit.hold_connection({tarpit.SOCKET_ENVIRON_KEY: conn.sock}, 30.0)
        worker.finish_request(conn, _finished(True))
    assert worker.handed[3:] == [(second, False)] and len(worker.held) == 1
    worker.alive = False  # a stopping worker lets every held connection go at once
    worker.release_due()
    assert worker.handed[4:] == [(first, True)] and not worker.held


@pytest.fixture(scope="module")
def production_server(tmp_path_factory):
    """``tessera serve --production`` (gunicorn, 1 process x 4 threads, the tarpit worker) on
    an empty managed collection with :data:`ADMIN_TOKEN`: its ``(host, port)``."""
    import os
    import socket
    import subprocess
    import sys

    root = tmp_path_factory.mktemp("served") / "collection"
    root.mkdir()
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    env = {**os.environ, "TESSERA_ADMIN_TOKEN": ADMIN_TOKEN, "TESSERA_PYODIDE_SNAPSHOT": "false"}
    log = root.parent / "serve.log"
    with open(log, "wb") as out:
        server = subprocess.Popen([sys.executable, "-m", "fitter.cli", "serve", str(root),
                                   "--production", "--port", str(port), "--processes", "1",
                                   "--threads", "4"], env=env, stdout=out,
                                  stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/api/objects", timeout=2).read()
                break
            except OSError:
                if server.poll() is not None or time.monotonic() > deadline:
                    pytest.fail("tessera serve --production did not start: " + log.read_text())
                time.sleep(0.2)
        yield "127.0.0.1", port
    finally:
        server.terminate()
        try:
            server.wait(15)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(10)


def _timed_get(conn, path: str, headers: dict[str, str] | None = None) -> tuple[int, float]:
    start = time.perf_counter()
    conn.request("GET", path, headers=headers or {})
    response = conn.getresponse()
    response.read()
    return response.status, time.perf_counter() - start


def test_a_locked_out_client_is_held_without_slowing_other_connections(production_server):
    import http.client

    from fitter.server.tarpit import REFUSED_HOLD_S

    host, port = production_server

    def connect() -> http.client.HTTPConnection:
        return http.client.HTTPConnection(host, port, timeout=30)

    # a refused token's connection: answered at once, its next request read a hold later
    attacker = connect()
    status, first = _timed_get(attacker, OBJECTS, bearer("short"))  # impossible shape
    assert status == 401
    held: list[tuple[int, float]] = []
    thread = threading.Thread(target=lambda: held.append(
        _timed_get(attacker, OBJECTS, bearer("short"))))
    thread.start()
    time.sleep(0.1)
    public = connect()
    status, public_s = _timed_get(public, "/api/objects")  # same address, other connection
    assert status == 200 and public_s < REFUSED_HOLD_S / 2
    status, fresh_s = _timed_get(connect(), OBJECTS, bearer("short"))
    assert status == 401 and fresh_s < REFUSED_HOLD_S / 2  # its first refusal is at once
    thread.join(30)
    assert held[0][0] == 401 and held[0][1] >= 0.9 * REFUSED_HOLD_S, held
    # lock the address out (FREE_FAILURES real scrypt failures, each on a new connection)
    for _ in range(FREE_FAILURES):
        assert _timed_get(connect(), OBJECTS, bearer(wrong_token()))[0] == 401
    locked = connect()
    locked.request("GET", OBJECTS, headers=bearer(wrong_token()))
    response = locked.getresponse()
    response.read()
    assert response.status == 429 and int(response.headers["Retry-After"]) >= 1
    status, fresh_s = _timed_get(connect(), OBJECTS, bearer(wrong_token()))
    assert status == 429 and fresh_s < REFUSED_HOLD_S / 2  # a new connection: at once
    status, again = _timed_get(locked, OBJECTS, bearer(wrong_token()))
    assert status in (401, 429) and again >= 0.9 * REFUSED_HOLD_S  # the held one waits
    status, public_s = _timed_get(connect(), "/api/objects")  # (gunicorn's keep-alive is 2 s)
    assert status == 200 and public_s < REFUSED_HOLD_S / 2


def test_attacking_connections_do_not_reduce_a_public_client_s_answers(production_server):
    """8 keep-alive connections send wrong tokens as fast as they are answered while one
    public client counts its answers: the tarpit lets each attacker make about one request
    per hold, and the public client keeps (noise allowing) its unloaded rate."""
    import http.client

    from fitter.server.tarpit import REFUSED_HOLD_S

    host, port = production_server
    seconds, attackers = 2.0, 8

    def public_client(counts: dict[str, int]) -> None:
        conn = http.client.HTTPConnection(host, port, timeout=30)
        end = time.perf_counter() + seconds
        while time.perf_counter() < end:
            status, _ = _timed_get(conn, "/api/objects")
            counts["ok" if status == 200 else "errors"] += 1

    def attacker(stop: threading.Event, sent: list[int]) -> None:
        conn = http.client.HTTPConnection(host, port, timeout=30)
        while not stop.is_set():
            sent.append(_timed_get(conn, OBJECTS, bearer(wrong_token()))[0])

    alone = {"ok": 0, "errors": 0}
    public_client(alone)
    stop, sent = threading.Event(), []
    threads = [threading.Thread(target=attacker, args=(stop, sent), daemon=True)
               for _ in range(attackers)]
    for thread in threads:
        thread.start()
    time.sleep(0.3)
    attacked = {"ok": 0, "errors": 0}
    public_client(attacked)
    stop.set()
    for thread in threads:
        thread.join(30)
    assert attacked["errors"] == 0 and alone["errors"] == 0
    assert set(sent) <= {401, 429, 503}
    # one request per connection at once, then one per hold (+1 for the last in flight)
    assert len(sent) <= attackers * ((seconds + 0.3) / REFUSED_HOLD_S + 2), len(sent)
    assert attacked["ok"] >= 0.5 * alone["ok"], (alone, attacked)
