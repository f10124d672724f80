"""The policy server: a Planner behind a websocket (websockets), messages in msgpack (adlpipe.deploy.wire).

One connection is one robot (or one simulated rollout). The conversation:

    client -> {"type": "hello", "protocol": 1, "token": "...", "seed": 0}      (token only if the server has one)
    server -> {"type": "ready", "policy": {...PlannerSpec...}}
    client -> {"type": "plan", "id": 7, "rgb": array, "affordance": array, "state": array, "command": array,
               "task": "wipe the nose"}                                        (fields as the spec says)
    server -> {"type": "plan", "id": 7, "waypoints": array, "times": array, "timing": {...}}
           or {"type": "error", "id": 7, "error": "field 'rgb' has shape (1, 64, 64), not (2, H, W, 3)"}

A message that breaks the protocol gets an error reply and the connection stays open; a wrong token gets an error
and the connection is closed. Plans run one at a time on one inference thread, in the order they arrive (several
robots are queued, not batched: a batch would make a robot's plan wait for another's frames). Every plan is logged
(--log, JSON lines): when it was received, how long it queued, the inference and the reply.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import json
import signal
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import torch
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from .planner import Observation, Planner
from .wire import MAX_MESSAGE_BYTES, PROTOCOL, WireError, array, dumps, field, loads

MAX_TASK_CHARS = 200
HELLO_TIMEOUT_S = 30.0  # a connection that never says hello does not hold a client slot


@dataclass
class ServeConfig:
    host: str = "127.0.0.1"  # localhost unless told otherwise
    port: int = 8765  # 0: any free port (printed, and written to port_file)
    token: str | None = None
    log: Path | None = None
    port_file: Path | None = None
    max_clients: int = 64


def observation_of(doc: dict, spec: Any) -> Observation:
    """A plan message's fields as an Observation, each checked for its type and dtype (the planner then checks
    shapes against the model)."""
    task = field(doc, "task", str, required=bool(spec.tasks)) or ""
    if len(task) > MAX_TASK_CHARS:
        raise WireError(f"field 'task' is {len(task)} characters, at most {MAX_TASK_CHARS}")
    float_types = (np.float32, np.float64)
    return Observation(
        rgb=array(doc, "rgb", (None, None, None, 3), (np.uint8,), required=spec.image),
        affordance=array(doc, "affordance", (None, None), float_types, required=spec.image),
        depth=array(doc, "depth", (None, None, None), float_types, required=False),
        state=array(doc, "state", (None, None), float_types, required=bool(spec.state_dim)),
        command=array(doc, "command", (3,), float_types, required=spec.needs_command),
        task=task)


class PolicyServer:
    def __init__(self, planner: Planner, config: ServeConfig, out: TextIO = sys.stderr) -> None:
        self.planner, self.config, self.out = planner, config, out
        self.infer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="inference")  # one plan at a time
        self.log_file = open(config.log, "a") if config.log else None  # noqa: SIM115 - closed in run()
        self.log_lock = threading.Lock()
        self.clients = 0
        self.plans = 0
        self.port: int | None = None

    def _log(self, row: dict) -> None:
        if self.log_file is not None:
            with self.log_lock:
                self.log_file.write(json.dumps(row) + "\n")
                self.log_file.flush()

    def _plan(self, obs: Observation, gen: torch.Generator) -> tuple[Any, float]:
        t0 = time.perf_counter()
        plan = self.planner.plan(obs, gen)
        return plan, t0

    async def handle(self, ws: ServerConnection) -> None:
        peer = str(ws.remote_address)
        if self.clients >= self.config.max_clients:
            await ws.close(1013, "server full")
            return
        self.clients += 1
        try:
            gen = await self._greet(ws)
            if gen is None:
                return
            async for raw in ws:
                received = time.time()
                t_recv = time.perf_counter()
                msg_id = None
                try:
                    doc = loads(raw)
                    msg_id = doc.get("id") if isinstance(doc.get("id"), int) else None
                    kind = field(doc, "type", str)
                    if kind != "plan":
                        raise WireError(f"message type {kind!r}: after hello only 'plan' is accepted")
                    obs = observation_of(doc, self.planner.spec)
                    seed = field(doc, "seed", int, required=False)
                    use = gen if seed is None else self.planner.placement.generator(seed)
                    plan, t_start = await asyncio.get_running_loop().run_in_executor(self.infer, self._plan, obs, use)
                except Exception as exc:  # noqa: BLE001 - any failure of one plan is that plan's error reply
                    error = (str(exc) if isinstance(exc, WireError)
                             else f"inference failed ({type(exc).__name__}: {str(exc)[:120]})")
                    await ws.send(dumps({"type": "error", "id": msg_id, "error": error}))
                    self._log({"peer": peer, "received": received, "error": error})
                    continue
                queue_ms = 1000.0 * (t_start - t_recv)
                reply = {"type": "plan", "id": msg_id, "waypoints": plan.waypoints, "times": plan.times,
                         "pixels": plan.pixels, "actions": plan.actions, "gripper": plan.gripper,
                         "timing": {"queue_ms": queue_ms, "inference_ms": plan.inference_ms}}
                t_send = time.perf_counter()
                await ws.send(dumps({k: v for k, v in reply.items() if v is not None}))
                self.plans += 1
                self._log({"peer": peer, "id": msg_id, "received": received, "queue_ms": round(queue_ms, 3),
                           "inference_ms": round(plan.inference_ms, 3),
                           "reply_ms": round(1000.0 * (time.perf_counter() - t_send), 3),
                           "total_ms": round(1000.0 * (time.perf_counter() - t_recv), 3)})
        except ConnectionClosed:
            pass  # a robot that went away mid-plan: its plan is dropped, the server goes on
        finally:
            self.clients -= 1

    async def _greet(self, ws: ServerConnection) -> torch.Generator | None:
        """The hello: protocol, token and the session's seed; the planner's spec in reply. None: refused."""
        while True:
            try:
                doc = loads(await asyncio.wait_for(ws.recv(), HELLO_TIMEOUT_S))
                if field(doc, "type", str) != "hello":
                    raise WireError("the first message is a hello ({'type': 'hello', 'protocol': 1, ...})")
                if field(doc, "protocol", int) != PROTOCOL:
                    raise WireError(f"protocol {doc['protocol']}: this server speaks {PROTOCOL}")
                token = field(doc, "token", str, required=False)
                if self.config.token is not None and not hmac.compare_digest(
                        (token or "").encode(), self.config.token.encode()):
                    await ws.send(dumps({"type": "error", "error": "wrong or missing token"}))
                    await ws.close(1008, "wrong token")
                    return None
                seed = field(doc, "seed", int, required=False) or 0
                if not 0 <= seed < 2**63:
                    raise WireError(f"seed {seed} is outside [0, 2**63)")
            except WireError as exc:
                await ws.send(dumps({"type": "error", "error": str(exc)}))
                continue
            except (asyncio.TimeoutError, TimeoutError):  # noqa: UP041 - distinct classes on Python 3.10
                await ws.send(dumps({"type": "error", "error": f"no hello within {HELLO_TIMEOUT_S:g} s"}))
                await ws.close(1008, "no hello")
                return None
            await ws.send(dumps({"type": "ready", "protocol": PROTOCOL, "policy": self.planner.spec.to_dict()}))
            return self.planner.placement.generator(seed)

    async def run(self, ready: threading.Event | None = None) -> None:
        stop = asyncio.get_running_loop().create_future()
        loop = asyncio.get_running_loop()
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(sig, self._stop, stop)
        try:
            async with serve(self.handle, self.config.host, self.config.port, max_size=MAX_MESSAGE_BYTES,
                             ping_interval=20, ping_timeout=60) as server:
                self.port = next(iter(server.sockets)).getsockname()[1]
                if self.config.port_file is not None:
                    tmp = self.config.port_file.with_name(self.config.port_file.name + ".tmp")
                    tmp.write_text(str(self.port))
                    tmp.replace(self.config.port_file)
                print(f"adlpipe serve: {self.planner.spec.extra['checkpoint']} ({self.planner.spec.model}, "
                      f"{self.planner.spec.steps} step(s), {self.planner.placement.device}) on "
                      f"ws://{self.config.host}:{self.port}" + (" (token required)" if self.config.token else ""),
                      file=self.out, flush=True)
                if ready is not None:
                    ready.set()
                await stop
        finally:
            self.infer.shutdown(wait=True, cancel_futures=True)
            if self.log_file is not None:
                self.log_file.close()
        print(f"adlpipe serve: stopped after {self.plans} plan(s)", file=self.out, flush=True)

    @staticmethod
    def _stop(stop: asyncio.Future) -> None:
        if not stop.done():
            stop.set_result(None)

    def serve_forever(self) -> None:
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(self.run())
