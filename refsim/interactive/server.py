"""The pose stream: newline-delimited JSON over TCP, bound to the loopback interface only
(docs/interactive.md, "Protocol").

Client to server, one JSON object per line:

- a pose ``{"t": 0.25, "base": [x, y, z], "direction": [dx, dy, dz]}`` (metres; the direction base to tip, any
  non-zero length; ``t`` optional, the sender's clock, not used);
- ``{"stop": true}``: end the session (the results file is closed and the replay written).

Server to client, one JSON object per line:

- on connecting, ``{"hello": "refsim interactive", "protocol": 1, ...}`` with the scene, dt, the mode and the
  current pose;
- after every step, ``{"step": ..., "time": ..., "force": [fx, fy, fz], "phase": ..., "events": [...], "base":
  [...], "direction": [...], "rtf": ...}`` (the force of the tissue on the needle [N], the haptic force);
- for a message it cannot use, ``{"error": "..."}`` naming the line and the defect (the connection stays open,
  the session goes on);
- when the session ends, ``{"done": true, "status": ..., "steps": ..., "output": ..., "replay": ...}``.

The server thread only reads, checks and queues; the steps (and their replies) are taken by the session's
thread. A client that stops reading its replies is disconnected after :data:`SEND_TIMEOUT` seconds of
blocked sending, so it cannot stall the simulation for the others.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import queue
import selectors
import socket
import threading

import numpy as np

from refsim.interactive.pose import PoseError, parse_pose

__all__ = ["MAX_LINE_BYTES", "PROTOCOL_VERSION", "PoseServer", "check_loopback"]

logger = logging.getLogger(__name__)

PROTOCOL_VERSION = 1
#: Longest accepted message line [bytes] (a pose is under 200 bytes).
MAX_LINE_BYTES = 65_536
#: A client whose replies cannot be sent for this long (it stopped reading them) is disconnected [s].
SEND_TIMEOUT = 5.0


def check_loopback(host: str) -> None:
    """Refuse a host that is not a loopback address (every address it resolves to must be one).

    Raises
    ------
    ValueError
        Naming the host and the address that is not loopback.
    """
    try:
        infos = socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP)
    except socket.gaierror as error:
        raise ValueError(f"--host {host}: cannot resolve it ({error})") from None
    for info in infos:
        address = ipaddress.ip_address(info[4][0].split("%")[0])
        if not address.is_loopback:
            raise ValueError(
                f"--host {host}: resolves to {address}, which is not a loopback address; the pose stream "
                "is bound to loopback only (127.0.0.1 or ::1): reach it from another machine through an "
                "SSH tunnel"
            )


class _Client:
    def __init__(self, connection: socket.socket, address) -> None:
        self.connection = connection
        self.address = address
        self.buffer = b""
        self.lines = 0
        self.lock = threading.Lock()
        self.open = True

    def send(self, message: dict) -> bool:
        data = (json.dumps(message, allow_nan=False) + "\n").encode()
        with self.lock:
            if not self.open:
                return False
            try:
                self.connection.sendall(data)
                return True
            except OSError:
                self.open = False
                return False


class PoseServer:
    """The pose stream's server on ``host:port`` (loopback only; port 0 picks a free port, see :attr:`port`).

    Parameters
    ----------
    port : TCP port, 0 to 65535.
    reach : Largest accepted distance of a base position from the origin [m].
    hello : Extra fields of the greeting (scene, dt, mode, ...); may be filled in before :meth:`start`.
    on_pose : Called from the server thread with (base, direction) for every valid pose (None: nobody);
        may be set before :meth:`start`.
    host : A loopback host name or address.

    Raises
    ------
    ValueError
        A host that is not loopback, a port out of range.
    OSError
        The port cannot be bound (in use).
    """

    def __init__(self, port: int, *, reach: float, hello: dict, on_pose, host: str = "127.0.0.1") -> None:
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"--socket {port!r}: expected a TCP port, 0 to 65535 (0: any free port)")
        check_loopback(host)
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        try:
            self._listener = socket.create_server((host, port), family=family)
        except OSError as error:
            raise OSError(
                error.errno, f"--socket {port}: cannot listen on {host}:{port}: {error.strerror}"
            ) from None
        self._listener.setblocking(False)
        self.host, self.port = self._listener.getsockname()[:2]
        self.reach = float(reach)
        self.hello = dict(hello)
        self.on_pose = on_pose
        self.stop_requested = threading.Event()
        self.connected = threading.Event()  # a client connected (at least once)
        self.disconnected = threading.Event()  # every client that connected has left
        self.poses: queue.Queue = queue.Queue()  # one entry per valid pose, when queue_poses (lock step)
        self.queue_poses = False  # lock step: each pose kept for its own step (real time: the latest wins)
        self._clients: dict[int, _Client] = {}
        self._clients_lock = threading.Lock()
        self._closing = threading.Event()
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._thread = threading.Thread(target=self._serve, name="refsim-pose-server", daemon=True)

    def start(self) -> PoseServer:
        self._thread.start()
        return self

    @property
    def client_count(self) -> int:
        with self._clients_lock:
            return len(self._clients)

    def broadcast(self, message: dict) -> None:
        """Send ``message`` to every connected client (one that cannot take it is dropped)."""
        with self._clients_lock:
            clients = list(self._clients.values())
        for client in clients:
            if not client.send(message):
                self._drop(client)

    def close(self, farewell: dict | None = None) -> None:
        """Send ``farewell`` to every client, then close every connection and the listener."""
        if farewell is not None:
            self.broadcast(farewell)
        self._closing.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        with self._clients_lock:
            clients = list(self._clients.values())
        for client in clients:
            self._drop(client)
        self._listener.close()
        self._selector.close()

    # ------------------------------------------------------------------ server thread

    def _serve(self) -> None:
        while not self._closing.is_set():
            for key, _ in self._selector.select(timeout=0.05):
                if key.data is None:
                    self._accept()
                else:
                    self._read(key.data)

    def _accept(self) -> None:
        try:
            connection, address = self._listener.accept()
        except BlockingIOError:
            return
        connection.settimeout(SEND_TIMEOUT)  # a client that stops reading cannot stall the steps
        connection.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # one small reply per step
        client = _Client(connection, address)
        with self._clients_lock:
            self._clients[connection.fileno()] = client
        self._selector.register(connection, selectors.EVENT_READ, client)
        self.disconnected.clear()
        self.connected.set()
        client.send({"hello": "refsim interactive", "protocol": PROTOCOL_VERSION, **self.hello})
        logger.info("pose stream: client %s connected", address)

    def _drop(self, client: _Client) -> None:
        with client.lock:
            client.open = False
        with self._clients_lock:
            known = self._clients.pop(client.connection.fileno(), None) is not None
            empty = not self._clients
        if known:
            try:
                self._selector.unregister(client.connection)
            except (KeyError, ValueError, OSError):
                pass
            client.connection.close()
            logger.info("pose stream: client %s left", client.address)
        if empty:
            self.disconnected.set()

    def _read(self, client: _Client) -> None:
        try:
            data = client.connection.recv(65_536)
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        client.buffer += data
        *lines, client.buffer = client.buffer.split(b"\n")
        for line in lines:
            client.lines += 1
            self._handle(client, line)
        if len(client.buffer) > MAX_LINE_BYTES:
            client.lines += 1
            client.buffer = b""
            client.send({"error": f"line {client.lines}: longer than {MAX_LINE_BYTES} bytes; dropped"})

    def _handle(self, client: _Client, line: bytes) -> None:
        where = f"line {client.lines}"
        if len(line) > MAX_LINE_BYTES:
            client.send({"error": f"{where}: longer than {MAX_LINE_BYTES} bytes; dropped"})
            return
        text = line.strip()
        if not text:
            return
        try:
            message = json.loads(text.decode("utf-8"), parse_constant=_refuse_constant)
        except (UnicodeDecodeError, ValueError) as error:
            client.send({"error": f"{where}: not a JSON object: {error}"})
            return
        if isinstance(message, dict) and "stop" in message:
            if message != {"stop": True}:
                client.send({"error": f'{where}: a stop message is exactly {{"stop": true}}'})
                return
            self.stop_requested.set()
            return
        try:
            base, direction = parse_pose(message, reach=self.reach)
        except PoseError as error:
            client.send({"error": f"{where}: {error}"})
            return
        if self.on_pose is not None:
            self.on_pose(np.asarray(base), np.asarray(direction))
        if self.queue_poses:
            self.poses.put((base, direction))


def _refuse_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")
