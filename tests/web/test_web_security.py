"""The drive server against hostile clients: only its own hosts and origins are served (DNS
rebinding refused on loopback and off, in both modes; `--allowed-host`), off loopback every page
path needs the key or a room's token, and every resource is bounded: the header timeout, the caps
per address and in total (600 idle connections against a server under `ulimit -n 512`), the
queue of messages waiting for a page that does not read, and a text frame that is not UTF-8."""

import asyncio
import http.client
import os
import resource
import select
import selectors
import socket
import subprocess
import sys
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, contextmanager

import pytest
from websockets.client import ClientProtocol
from websockets.exceptions import ConnectionClosed, InvalidMessage, InvalidStatus
from websockets.frames import Frame, Opcode
from websockets.sync.client import connect
from websockets.uri import parse_uri

from helpers_web import client, drive_server, receive, send
from test_web_browser import browser, wait_for  # noqa: F401 (the Chromium fixture)
from trafficweaving.cli import main
from trafficweaving.data.trials import load_trials
from trafficweaving.scenario import LANE_DIVIDER_Y, MIN_TRIAL_STEPS
from trafficweaving.web.hosts import HostPolicy, parse_allowed_host
from trafficweaving.web.limits import ACCEPT_BACKLOG, MAX_CONNECTIONS, RESERVED_FDS, ConnectionLimits
from trafficweaving.web.room import OUTBOX_LIMIT, OUTBOX_STATE_BACKLOG, Member

EVIL = "evil.example"


# ---------------------------------------------------------------- clients that choose their Host
def port_of(url: str) -> int:
    return urllib.parse.urlsplit(url).port


def get(port: int, target: str = "/", host: str | None = None, headers: dict | None = None):
    """``GET target`` at 127.0.0.1:``port`` with ``Host: host`` (default the address itself):
    (status, response headers, body)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        connection.request("GET", target, headers={"Host": host or f"127.0.0.1:{port}", **(headers or {})})
        response = connection.getresponse()
        return response.status, response.headers, response.read()
    finally:
        connection.close()


def ws(port: int, query: str = "", host: str | None = None, origin: str | None = None):
    """A WebSocket to 127.0.0.1:``port`` whose handshake names ``host`` (``Host``) and ``origin``."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    return connect(f"ws://{host or f'127.0.0.1:{port}'}/ws{query}", sock=sock, origin=origin, open_timeout=5,
                   max_size=None, max_queue=None)


def refused_ws(port: int, query: str = "", host: str | None = None, origin: str | None = None) -> int:
    """The HTTP status of a WebSocket handshake that must be refused."""
    with pytest.raises(InvalidStatus) as refused:
        ws(port, query, host, origin).close()
    return refused.value.response.status_code


# ---------------------------------------------------------------- hosts and origins
def test_the_host_policy_names_only_this_server():
    loopback = HostPolicy("127.0.0.1", ("127.0.0.1", 8123))
    for host in ("127.0.0.1:8123", "localhost:8123", "LocalHost:8123", "[::1]:8123", "127.4.5.6:8123"):
        assert loopback.allows(host, "127.0.0.1"), host
    for host in (None, "", f"{EVIL}:8123", EVIL, "127.0.0.1", "127.0.0.1:8124", "localhost:81234", "localhost.:8123",
                 "127.0.0.1.nip.io:8123", "localhost:8123:1", "::1:8123", "[::1", "user@localhost:8123",
                 "10.0.0.1:8123", "[::ffff:127.0.0.1]:8123", "localhost:8123/x"):
        assert not loopback.allows(host, "127.0.0.1"), host
    assert HostPolicy("127.0.0.1", ("127.0.0.1", 80)).allows("localhost", "127.0.0.1")  # no port: 80
    for origin in (None, "http://localhost:8123", "http://127.0.0.1:8123", "http://[::1]:8123"):
        assert loopback.allows_origin(origin, "127.0.0.1"), origin
    for origin in ("null", "", f"http://{EVIL}:8123", "http://localhost:8124", "http://localhost",
                   "https://localhost:8123", "http://localhost:8123/", "file://", "http://a@localhost:8123"):
        assert not loopback.allows_origin(origin, "127.0.0.1"), origin

    anywhere = HostPolicy("0.0.0.0", ("0.0.0.0", 8123), [parse_allowed_host("Lab-PC.example"),
                                                         parse_allowed_host("proxy.example:9000")])
    assert anywhere.allows("192.168.1.20:8123", "192.168.1.20")  # the address the request arrived on
    assert anywhere.allows("192.168.1.20:8123", "::ffff:192.168.1.20")
    assert not anywhere.allows("192.168.1.21:8123", "192.168.1.20")
    assert not anywhere.allows("localhost:8123", "192.168.1.20")  # loopback names only over loopback
    assert not anywhere.allows("0.0.0.0:8123", "192.168.1.20")
    assert anywhere.allows("lab-pc.example:8123", "192.168.1.20")
    assert anywhere.allows("proxy.example:9000", "10.0.0.1")
    assert not anywhere.allows("proxy.example:8123", "10.0.0.1") and not anywhere.allows("lab-pc.example:9000", None)
    assert anywhere.allows_origin("http://lab-pc.example:8123", "10.0.0.1")
    named = HostPolicy("lab-pc.example", ("192.168.1.20", 8123))
    assert named.allows("lab-pc.example:8123", "192.168.1.20") and named.allows("192.168.1.20:8123", None)


def test_allowed_host_values_are_parsed_and_bad_ones_are_one_line_errors(tmp_path, capsys):
    assert parse_allowed_host("Lab-PC.local") == ("lab-pc.local", None)
    assert parse_allowed_host("lab-pc.local:8000") == ("lab-pc.local", 8000)
    assert parse_allowed_host("10.0.0.2") == ("10.0.0.2", None)
    assert parse_allowed_host("fe80::1") == ("fe80::1", None)
    assert parse_allowed_host("[fe80::1]:9000") == ("fe80::1", 9000)
    for bad in ("", "lab pc", "lab:0", "lab:65536", "lab:", ":8000", "[::1", "a..b", "-lab.local", "lab:80:80",
                "http://lab", "lab/x", "x" * 300, "é.local"):
        assert main(["drive", "--no-browser", "--mode", "human-human", "--port", "0", "--out", str(tmp_path / "d"),
                     "--allowed-host", "lab.local", f"--allowed-host={bad}"]) == 2, bad
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "trafficweaving drive: error: --allowed-host" in err and repr(bad) in err, err


@contextmanager
def server_with_key(tmp_path, mode, host, **options):
    """A drive server; yields (port, the key's query: '' on loopback)."""
    with drive_server(tmp_path, mode=mode, host=host, **options) as url:
        yield port_of(url), ("?" + url.split("?", 1)[1]) if "?" in url else ""


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["human-human", "robot"])
@pytest.mark.parametrize("host", ["127.0.0.1", "0.0.0.0"])
def test_dns_rebinding_is_refused_in_both_modes_on_loopback_and_off(tmp_path, mode, host):
    with server_with_key(tmp_path, mode, host) as (port, key):
        evil = f"{EVIL}:{port}"
        for target in (f"/{key}", "/static/drive.js", "/static/index.html", f"/ws{key}"):
            status, _, body = get(port, target, host=evil)
            assert status == 400 and b"not this server" in body, (target, status)
        assert refused_ws(port, key, host=evil, origin=f"http://{evil}") == 403  # the rebound page itself
        assert refused_ws(port, key, host=evil) == 403
        assert get(port, f"/{key}", host=f"127.0.0.1:{port + 1}")[0] == 400  # a loopback name, another port
        assert refused_ws(port, key, origin=f"http://localhost:{port + 1}") == 403
        assert refused_ws(port, key, origin=f"http://{evil}") == 403  # another site's page
        assert refused_ws(port, key, origin="null") == 403
        with socket.create_connection(("127.0.0.1", port), timeout=10) as raw:  # no Host at all (HTTP/1.0)
            raw.sendall(f"GET /{key} HTTP/1.0\r\n\r\n".encode())
            assert raw.recv(100).startswith(b"HTTP/1.1 400")
        assert not list(tmp_path.glob("drive_*.parquet"))
        # this server's own names are served
        for name in (f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}", f"127.9.9.9:{port}"):
            status, _, body = get(port, f"/{key}", host=name)
            assert status == 200 and b"<canvas" in body, name
        with ws(port, key, host=f"localhost:{port}", origin=f"http://localhost:{port}") as page:
            assert receive(page)["type"] == "welcome"


def test_allowed_host_names_are_served_and_no_others(tmp_path):
    with server_with_key(tmp_path, "human-human", "0.0.0.0",
                         allowed_hosts=["Lab-PC.example", "proxy.example:9000"]) as (port, key):
        assert get(port, f"/{key}", host=f"lab-pc.example:{port}")[0] == 200
        assert get(port, f"/{key}", host="proxy.example:9000")[0] == 200
        assert get(port, f"/{key}", host=f"proxy.example:{port}")[0] == 400
        assert get(port, f"/{key}", host="lab-pc.example:9000")[0] == 400
        assert get(port, f"/{key}", host=f"other.example:{port}")[0] == 400
        with ws(port, key, host=f"lab-pc.example:{port}", origin=f"http://lab-pc.example:{port}") as page:
            assert receive(page)["type"] == "welcome"
        assert refused_ws(port, key, host=f"lab-pc.example:{port}", origin=f"http://other.example:{port}") == 403


# ---------------------------------------------------------------- the key covers every page path
def test_off_loopback_the_page_files_need_the_pass_the_keyed_page_sets(tmp_path):
    with server_with_key(tmp_path, "human-human", "0.0.0.0") as (port, key):
        for target in ("/static/index.html", "/static/drive.js", "/static/drive.css", "/", "/?key=wrong",
                       "/?key=%C3%A9", "/?room=1&token=%C3%A9"):
            status, headers, body = get(port, target)
            assert status == 403 and b"<canvas" not in body and "set-cookie" not in headers, target
        status, headers, body = get(port, "/" + key)
        assert status == 200 and b'src="/static/drive.js"' in body
        cookie = headers["set-cookie"]
        attributes = {part.strip().lower() for part in cookie.split(";")}
        assert {"httponly", "samesite=strict", "path=/static"} <= attributes, cookie
        page_pass = cookie.split(";")[0]
        assert key.split("=")[1] not in page_pass  # the pass is not the key: it opens no room
        for name in ("drive.js", "draw.js", "input.js", "connection.js", "drive.css"):
            assert get(port, f"/static/{name}", headers={"Cookie": page_pass})[0] == 200, name
        assert get(port, "/static/drive.js", headers={"Cookie": page_pass[:-2] + "xx"})[0] == 403
        assert refused_ws(port) == 403  # the pass is no key
        with ws(port, key) as first:  # a join link's page gets the pass too
            assert receive(first)["type"] == "welcome"
            join = receive(first)["join"]
            status, headers, _ = get(port, join)
            assert status == 200 and headers["set-cookie"].split(";")[0] == page_pass


@pytest.mark.slow
def test_a_keyed_page_and_a_join_link_load_their_scripts_in_a_real_browser(browser, tmp_path):
    with server_with_key(tmp_path, "human-human", "0.0.0.0") as (port, key):
        base = f"http://127.0.0.1:{port}"
        stranger = browser.new_context()
        assert stranger.new_page().goto(f"{base}/static/index.html").status == 403
        first = browser.new_context().new_page()
        first.goto(f"{base}/{key}")
        wait_for(first, "window.drive.phase === 'idle'")  # its scripts ran and it is in a room
        join = wait_for(first, "document.getElementById('join-link').value")
        assert "key=" not in join
        second = browser.new_context().new_page()  # another browser: the join link alone
        second.goto(join)
        wait_for(second, "window.drive.phase === 'idle'")
        assert wait_for(first, "window.drive.room && window.drive.room.seats.every(Boolean)")


# ---------------------------------------------------------------- connections bounded
def closed_by_server(sock: socket.socket, within: float) -> bool:
    """Whether the server closes ``sock`` within ``within`` s (what it sends first is skipped)."""
    deadline = time.monotonic() + within
    while (left := deadline - time.monotonic()) > 0:
        if select.select([sock], [], [], left)[0]:
            try:
                if not sock.recv(65536):
                    return True
            except ConnectionError:
                return True
    return False


def idle(port: int, source: str = "127.0.0.1", partial: bool = False) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10, source_address=(source, 0))
    if partial:
        sock.sendall(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUser-Agent: slo".encode())
    return sock


@pytest.mark.slow
def test_connections_that_do_not_send_a_request_in_time_are_closed_but_pages_stay(tmp_path):
    limits = ConnectionLimits(total=64, per_address=32, header_timeout_s=1.0)
    with drive_server(tmp_path, mode="human-human", limits=limits) as url, client(url) as page:
        port = port_of(url)
        silent, partial, kept = idle(port), idle(port, partial=True), idle(port)
        kept.sendall(f"GET /static/drive.css HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
        assert kept.recv(20).startswith(b"HTTP/1.1 200")
        started = time.monotonic()
        for _ in range(4):  # a header a byte at a time does not keep it open
            time.sleep(0.2)
            partial.sendall(b"w")
        for sock in (silent, partial, kept):
            assert closed_by_server(sock, 3.0)
            sock.close()
        assert time.monotonic() - started < 3.5  # (the timeout's default is 5 s)
        assert receive(page)["type"] == "room"
        send(page, {"type": "participant", "driver": 3})  # the page, idle as long, still works
        assert receive(page)["participants"] == [3, None]
        assert get(port)[0] == 200


@pytest.mark.slow
def test_at_a_cap_the_oldest_waiting_connection_is_closed_never_a_page(tmp_path):
    limits = ConnectionLimits(total=7, per_address=4, header_timeout_s=30.0)
    with drive_server(tmp_path, mode="human-human", limits=limits) as url, ExitStack() as stack:
        port = port_of(url)
        a = stack.enter_context(client(url))
        room = receive(a)
        b = stack.enter_context(client(url, "?" + room["join"].split("?")[1]))
        first, second = idle(port), idle(port, partial=True)  # 127.0.0.1 at its cap of 4
        time.sleep(0.2)
        third = idle(port)
        assert closed_by_server(first, 2.0) and not closed_by_server(second, 0.3)
        assert get(port)[0] == 200  # a request closes the next oldest waiting connection
        assert closed_by_server(second, 2.0) and not closed_by_server(third, 0.3)
        pages = [a, b, stack.enter_context(client(url))]  # (the request's connection closed when done)
        assert not closed_by_server(third, 0.3)
        pages.append(stack.enter_context(client(url)))  # a new room's page: the last waiting one closed for it
        assert closed_by_server(third, 2.0)
        with pytest.raises((InvalidMessage, ConnectionClosed, OSError)):  # closed before or during the handshake
            ws(port).close()  # four pages of 127.0.0.1 drive: no room for a fifth, and none is closed for it
        others = [idle(port, "127.0.0.2"), idle(port, "127.0.0.2"), idle(port, "127.0.0.3")]
        time.sleep(0.2)
        newest = idle(port, "127.0.0.4")  # the total cap of 7: the oldest waiting anywhere goes
        assert closed_by_server(others[0], 2.0) and not any(closed_by_server(s, 0.2) for s in others[1:] + [newest])
        for page in pages:  # every page still works
            send(page, {"type": "abort"})
            while (message := receive(page))["type"] != "error":
                pass
            assert "without a running trial" in message["error"]


def test_a_page_whose_messages_pile_up_unsent_is_dropped():
    async def scenario():
        stuck = asyncio.Event()

        async def never_delivers(text):
            await stuck.wait()

        dropped = []
        member = Member(never_delivers, lambda: dropped.append(True))
        member.open()
        await asyncio.sleep(0)
        for k in range(3 * OUTBOX_STATE_BACKLOG):
            member.post(f"state {k}", droppable=True)
        assert member.outbox.qsize() == OUTBOX_STATE_BACKLOG  # states wait no further
        sizes = []
        for k in range(OUTBOX_LIMIT + 100):
            member.post(f"error {k}")
            sizes.append(member.outbox.qsize())
        assert max(sizes) == OUTBOX_LIMIT and dropped == [True] and member.dropped
        assert member.outbox.qsize() == 0
        member.post("one more")
        assert member.outbox.qsize() == 0 and dropped == [True]
        await member.close()

    with ThreadPoolExecutor(1) as pool:  # a loop of its own (Playwright's may be running in this thread)
        pool.submit(asyncio.run, scenario()).result()


# ---------------------------------------------------------------- a server under `ulimit -n 512`
FD_LIMIT = 512


@pytest.fixture(scope="module")
def small_server(tmp_path_factory):
    """`trafficweaving drive --mode human-human` in a process limited to 512 open files; yields
    (port, its folder, a function returning its log so far, its process id)."""
    folder = tmp_path_factory.mktemp("small")
    log_path = folder / "server.log"
    with open(log_path, "w") as log:
        process = subprocess.Popen(
            [sys.executable, "-m", "trafficweaving", "drive", "--mode", "human-human", "--port", "0", "--countdown",
             "0", "--no-browser", "--out", str(folder / "drives")],
            stdout=subprocess.PIPE, stderr=log, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT)))
    try:
        line = process.stdout.readline()
        assert "open http://127.0.0.1:" in line, (line, log_path.read_text())
        port = port_of(line.split("open ")[1].split()[0])
        yield port, folder / "drives", log_path.read_text, process.pid
    finally:
        process.terminate()
        process.wait(30)


def outward_steer(start_y: float) -> float:
    """Steering towards the road's edge beside a car's starting lane (negative: left, up in y)."""
    return -1.0 if start_y > LANE_DIVIDER_Y else 1.0


def drive_a_trial(url: str) -> dict:
    """Two pages meet in a room and drive a trial until one leaves the road; the ``ended`` message."""
    with client(url) as a:
        room = receive(a)
        with client(url, "?" + room["join"].split("?")[1]) as b:
            send(a, {"type": "start", "initial_condition": 4})
            pages = {}
            for page in (a, b):
                while (message := receive(page))["type"] != "started":
                    pass
                pages[message["cars"][0]] = page
                start_y = [state[1] for state in message["states"]]
            seq = 0
            while (message := receive(a))["type"] != "ended":
                if message["type"] == "state" and message["step"] > MIN_TRIAL_STEPS:
                    seq += 1
                    for car, page in pages.items():
                        send(page, {"type": "controls", "seq": seq, "car": car, "throttle": 0.3, "brake": 0.0,
                                    "steer": outward_steer(start_y[car])})
            return message


def open_idle(port: int, count: int) -> list[socket.socket]:
    """``count`` connections opened at once (half of them then send part of a request header)."""
    sockets, selector = [], selectors.DefaultSelector()
    for _ in range(count):
        sock = socket.socket()
        sock.setblocking(False)
        sock.connect_ex(("127.0.0.1", port))
        selector.register(sock, selectors.EVENT_WRITE)
        sockets.append(sock)
    deadline, waiting = time.monotonic() + 20, count
    while waiting and time.monotonic() < deadline:
        for key, _ in selector.select(1):
            selector.unregister(key.fileobj)
            waiting -= 1
            assert not key.fileobj.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR)
    assert not waiting
    for sock in sockets[1::2]:
        try:
            sock.send(f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUser-Agent: slo".encode())
        except OSError:  # already closed by the server
            pass
    return sockets


@pytest.mark.slow
def test_600_idle_connections_leave_a_server_under_ulimit_512_able_to_drive(small_server):
    port, folder, server_log, pid = small_server
    per_address = min(MAX_CONNECTIONS, FD_LIMIT - RESERVED_FDS - 4 * ACCEPT_BACKLOG) // 2
    idlers = open_idle(port, 600)
    open_files = lambda: len(os.listdir(f"/proc/{pid}/fd"))  # noqa: E731
    try:
        deadline = time.monotonic() + 10  # the server accepts the connections the kernel has queued at its pace
        while open_files() <= per_address and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.5)
        assert per_address < open_files() <= per_address + 16  # its cap for one address is full, no more
        ended = drive_a_trial(f"http://127.0.0.1:{port}/")
        assert ended["reason"] == "off_road" and ended["file"] and ended["steps"] > MIN_TRIAL_STEPS
        status, _, body = get(port)
        assert status == 200 and b"<canvas" in body
    finally:
        for sock in idlers:
            sock.close()
    assert (folder / os.path.basename(ended["file"])).exists()
    log = server_log()
    assert "Too many open files" not in log and "Traceback" not in log and "out of system resource" not in log, log


@pytest.mark.slow
def test_a_text_frame_that_is_not_utf8_closes_that_page_with_one_log_line(small_server):
    port, _, server_log, _ = small_server
    before = server_log().count("\n")
    with client(f"http://127.0.0.1:{port}/") as page:
        with page.protocol_mutex:
            page.protocol.send_frame(Frame(Opcode.TEXT, b'{"type": "abort"\xff}'))
            page.send_data()
        with pytest.raises(ConnectionClosed) as closed:
            while True:
                page.recv(timeout=10)
        assert closed.value.rcvd.code == 1007
    time.sleep(0.2)
    new = server_log().splitlines()[before:]
    assert len(new) == 1 and "not UTF-8" in new[0] and "Traceback" not in server_log(), new
    with client(f"http://127.0.0.1:{port}/") as page:  # the server is fine
        assert receive(page)["type"] == "room"


def flood_without_reading(port: int) -> float:
    """A page that sends refused messages as fast as it can and reads nothing after the handshake;
    the seconds until the server drops it."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(10)
        sock.connect(("127.0.0.1", port))
        protocol = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}/ws"))
        protocol.send_request(protocol.connect())
        sock.sendall(b"".join(protocol.data_to_send()))
        while not protocol.events_received():
            protocol.receive_data(sock.recv(1))  # byte by byte: nothing after the handshake is read
        started = time.monotonic()
        try:
            while time.monotonic() - started < 30:
                protocol.send_text(b"not json")  # each is answered with an error
                sock.sendall(b"".join(protocol.data_to_send()))
        except OSError:  # dropped
            return time.monotonic() - started
        return float("inf")


@pytest.mark.slow
def test_a_page_that_floods_and_never_reads_is_dropped_while_another_room_drives(small_server):
    port, _, server_log, _ = small_server
    before = server_log().count("\n")
    with ThreadPoolExecutor(1) as pool:
        flood = pool.submit(flood_without_reading, port)
        ended = drive_a_trial(f"http://127.0.0.1:{port}/")
        assert flood.result() < 15
    assert ended["reason"] == "off_road" and ended["file"]
    record = load_trials(ended["file"]).metadata["drive"]
    assert record["step_period"]["mean_s"] < 0.13  # the other room kept its 10 Hz
    time.sleep(0.2)
    new = server_log().splitlines()[before:]
    assert len(new) == 1 and "does not read" in new[0], new
