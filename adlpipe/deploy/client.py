"""The robot-side client of `adlpipe serve`: numpy, msgpack and websockets only (no torch), a few lines to use.

    from adlpipe.deploy.client import PolicyClient
    with PolicyClient("ws://gpu-box:8765", token="...") as client:
        print(client.policy)                       # what the policy expects: n_obs, state_dim, rate_hz, tasks ...
        plan = client.plan(rgb=frames, affordance=amap, state=state, command=last_command, task="wipe the nose")
        plan["waypoints"], plan["times"]           # (Tp, 3) metres in base_link, seconds after the observation
"""

from __future__ import annotations

from contextlib import ExitStack
from typing import Any

import numpy as np
from websockets.sync.client import ClientConnection, connect

from .wire import MAX_MESSAGE_BYTES, PROTOCOL, dumps, loads


class ServerError(RuntimeError):
    """The server refused a request (its one-line reason), or the connection was refused."""


class PolicyClient:
    def __init__(self, url: str, token: str | None = None, seed: int = 0, timeout_s: float = 30.0) -> None:
        """Connect and say hello. seed: this session's sampler noise (the same seed, the same plans)."""
        self.timeout_s = timeout_s
        self._stack = ExitStack()
        self._ws: ClientConnection = self._stack.enter_context(
            connect(url, max_size=MAX_MESSAGE_BYTES, open_timeout=timeout_s, close_timeout=2))
        self._next_id = 0
        hello: dict[str, Any] = {"type": "hello", "protocol": PROTOCOL, "seed": int(seed)}
        if token is not None:
            hello["token"] = token
        try:
            self.policy: dict = self._ask(hello)["policy"]
        except BaseException:
            self.close()
            raise

    def _ask(self, doc: dict) -> dict:
        self._ws.send(dumps(doc))
        reply = loads(self._ws.recv(timeout=self.timeout_s))
        if reply.get("type") == "error":
            raise ServerError(str(reply.get("error")))
        return reply

    def plan(self, task: str = "", **arrays: np.ndarray | None) -> dict:
        """One plan: rgb (To, H, W, 3) uint8, affordance (H, W), depth (To, H, W), state (To, D), command (3,), as
        the policy's spec asks (self.policy). Returns waypoints, times, timing (and pixels or actions where the
        policy plans them)."""
        self._next_id += 1
        doc: dict[str, Any] = {"type": "plan", "id": self._next_id, "task": task}
        doc.update({k: np.asarray(v) for k, v in arrays.items() if v is not None})
        reply = self._ask(doc)
        if reply.get("id") != self._next_id:
            raise ServerError(f"reply to request {reply.get('id')}, expected {self._next_id}")
        return reply

    def close(self) -> None:
        self._stack.close()

    def __enter__(self) -> PolicyClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
