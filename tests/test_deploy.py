"""Deployment on real processes over a real socket: the public planning API, `adlpipe serve` and its torch-free
client, the ROS-free core of the ROS 2 node fed a real bag, closed loop in MuJoCo through the server (the same plans
as in-process), every trial a bag that `adlpipe trials` decides from, and hostile messages answered one by one."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import msgpack
import numpy as np
import pytest
import torch
from conftest import REPO, one_line_error, run_module
from websockets.sync.client import connect

from adlpipe.dataset import schema
from adlpipe.dataset.loader import Normalizer, normalize_state, observation_from_arrays
from adlpipe.deploy import Observation, Planner
from adlpipe.deploy.client import PolicyClient, ServerError
from adlpipe.deploy.wire import WireError, dumps, loads, pack_array
from adlpipe.plumbing.runtime import Placement
from adlpipe.policy.inference import predict


def start_server(model: Path, root: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    """A real `python -m adlpipe.serve` process on a free port; (process, ws:// url) once it listens."""
    port_file = root / f"port_{time.monotonic_ns()}"
    proc = subprocess.Popen([sys.executable, "-m", "adlpipe.serve", str(model), "--port", "0", "--port-file",
                             str(port_file), *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=REPO)
    deadline = time.monotonic() + 60
    while not port_file.exists():
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise AssertionError(f"serve did not start: {proc.communicate()[1]}")
        time.sleep(0.05)
    return proc, f"ws://127.0.0.1:{port_file.read_text()}"


def stop(proc: subprocess.Popen) -> tuple[int, str]:
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    return proc.returncode, err


@pytest.fixture(scope="module")
def served(closed_loop_model, tmp_path_factory: pytest.TempPathFactory):
    """(model, url, token, log, process): the tiny closed-loop FM served with a token and a plan log."""
    root = tmp_path_factory.mktemp("serve")
    token = root / "token"
    token.write_text("s3cret\n")
    log = root / "plans.jsonl"
    proc, url = start_server(closed_loop_model[1], root, "--token-file", str(token), "--log", str(log))
    yield closed_loop_model[1], url, "s3cret", log, proc
    code, err = stop(proc)
    assert code == 0 and "stopped after" in err, err


def episode_observation(data: Path, k: int = 4) -> Observation:
    """The observation a robot would have sent at frame k of a recorded episode: the last two frames, the measured
    tcp and gripper at each, and the command then as the anchor."""
    with h5py.File(data) as f:
        name = schema.episode_names(f)[0]
        g = f[schema.EPISODES][name]
        fr = g["frames"]
        rgb = fr["rgb"][k - 1:k + 1]
        state = np.concatenate([fr["ee_pos"][k - 1:k + 1], fr["gripper"][k - 1:k + 1][:, None]], 1).astype(float)
        command = fr["action"][k, :3].astype(float)
        return Observation(rgb=rgb, affordance=g["affordance"][()], state=state, command=command,
                           task=str(g.attrs["task"]))


def test_the_planner_plans_as_replay_predicts_in_the_base_frame(closed_loop_model, ingested: Path) -> None:
    """The public API's plan is the model's own prediction through the dataset's observation builder (the path
    replay took before the API existed), anchored at the command: waypoints in metres at 10 Hz, 16 of them."""
    model = closed_loop_model[1]
    planner = Planner.load(model)
    obs = episode_observation(ingested)
    plan = planner.plan(obs, torch.Generator().manual_seed(3))
    assert plan.waypoints.shape == (16, 3) and plan.pixels is None and plan.gripper is None
    np.testing.assert_allclose(plan.times, np.arange(1, 17) / 10.0)
    assert plan.inference_ms > 0
    # the same prediction made by hand, as closed-loop replay made it
    from adlpipe.policy.checkpoint import load_policy

    policy, ck = load_policy(model / "best.pt")
    image = np.concatenate([observation_from_arrays(obs.rgb[i], obs.affordance, None, policy.cfg.image_size, False)
                            for i in range(2)])
    x = (torch.from_numpy(image)[None], normalize_state(obs.state, ck["stats"])[None])
    pred = predict(policy, x, 1, None, torch.Generator().manual_seed(3), Placement())
    want = obs.command + Normalizer(ck["stats"]).unnormalize(pred)[0, :, 2:].numpy().astype(float)
    np.testing.assert_array_equal(plan.waypoints, want)
    assert np.abs(plan.waypoints - obs.command).max() < 0.5  # metres from the anchor, not pixels
    # the same seed, the same plan; another seed, another plan
    np.testing.assert_array_equal(planner.plan(obs, torch.Generator().manual_seed(3)).waypoints, plan.waypoints)
    assert not np.array_equal(planner.plan(obs, torch.Generator().manual_seed(4)).waypoints, plan.waypoints)


@pytest.mark.parametrize(("change", "message"), [
    ({"rgb": np.zeros((1, 64, 64, 3), np.uint8)}, "field 'rgb' has shape (1, 64, 64, 3), not (2, H, W, 3)"),
    ({"rgb": np.zeros((2, 64, 64, 3), np.float32)}, "field 'rgb' has dtype float32, not uint8"),
    ({"affordance": np.zeros((32, 32), np.float32)}, "field 'affordance' has shape (32, 32), not the image's"),
    ({"state": np.zeros((2, 3))}, "field 'state' has shape (2, 3), not (2, 4)"),
    ({"command": None}, "missing field 'command'"),
    ({"state": np.full((2, 4), np.nan)}, "field 'state' holds NaN"),
])
def test_an_observation_that_does_not_fit_is_named(closed_loop_model, ingested: Path, change: dict,
                                                   message: str) -> None:
    obs = episode_observation(ingested)
    for k, v in change.items():
        setattr(obs, k, v)
    with pytest.raises(WireError, match=None) as err:
        Planner.load(closed_loop_model[1]).plan(obs)
    assert message in str(err.value)


def test_served_plans_are_the_in_process_plans_and_each_is_logged(served, ingested: Path) -> None:
    model, url, token, log, _ = served
    obs = episode_observation(ingested)
    planner = Planner.load(model)
    with PolicyClient(url, token=token, seed=11) as client:
        assert client.policy["model"] == "fm_cnn" and client.policy["n_obs"] == 2
        assert client.policy["needs_command"] and client.policy["rate_hz"] == 10.0
        gen = torch.Generator().manual_seed(11)  # the session's seed: plan after plan from one generator
        for _ in range(3):
            plan = client.plan(task=obs.task, rgb=obs.rgb, affordance=obs.affordance, state=obs.state,
                               command=obs.command)
            # float32 sums in another order on this process's threads than on the server's one: within 1e-6 m
            np.testing.assert_allclose(plan["waypoints"], planner.plan(obs, gen).waypoints, rtol=0, atol=1e-6)
            np.testing.assert_allclose(plan["times"], np.arange(1, 17) / 10.0)
            assert plan["timing"]["inference_ms"] > 0
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    plans = [r for r in rows if "inference_ms" in r]
    assert len(plans) >= 3
    assert all(r["received"] > 1.7e9 and r["queue_ms"] >= 0 and r["reply_ms"] >= 0 and r["total_ms"] >= r[
        "inference_ms"] for r in plans)


def test_the_robot_side_client_needs_no_torch(served, ingested: Path, tmp_path: Path) -> None:
    """The client in a process where importing torch fails: numpy, msgpack and websockets are enough."""
    _, url, token, _, _ = served
    obs = episode_observation(ingested)
    np.savez(tmp_path / "obs.npz", rgb=obs.rgb, affordance=obs.affordance, state=obs.state, command=obs.command)
    script = f"""
import sys
sys.modules["torch"] = None  # any import of torch now raises ImportError
import numpy as np
from adlpipe.deploy.client import PolicyClient
o = np.load({str(tmp_path / "obs.npz")!r})
with PolicyClient({url!r}, token={token!r}) as c:
    p = c.plan(task={obs.task!r}, rgb=o["rgb"], affordance=o["affordance"], state=o["state"], command=o["command"])
print(p["waypoints"].shape, "torch" in sys.modules and sys.modules["torch"] is not None)
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "(16, 3) False"


def hostile_messages(valid: dict, n: int, rng: np.random.Generator) -> list[bytes | str]:
    """n malformed or hostile plan messages: random bytes, truncated frames, wrong shapes and dtypes, arrays whose
    bytes do not match their shape, huge declared sizes, wrong types, deep nesting, unknown types, text frames."""
    good = dumps(valid)
    makers = [
        lambda: rng.bytes(int(rng.integers(0, 200))),
        lambda: good[:int(rng.integers(1, len(good) - 1))],
        lambda: dumps({**valid, "rgb": np.zeros((int(rng.integers(3, 5)), 8, 8, 3), np.uint8)}),
        lambda: dumps({**valid, "rgb": valid["rgb"].astype(np.float64)}),
        lambda: dumps({**valid, "state": np.zeros((2, int(rng.integers(5, 9))))}),
        lambda: dumps({**valid, "command": np.zeros(4)}),
        lambda: dumps({**valid, "command": "up"}),
        lambda: dumps({**valid, "task": 7}),
        lambda: dumps({**valid, "task": "x" * 300}),
        lambda: dumps({**valid, "type": "shutdown"}),
        lambda: dumps({**valid, "seed": True}),
        lambda: dumps({k: v for k, v in valid.items() if k != "rgb"}),
        lambda: dumps({**valid, "rgb": {**pack_array(valid["rgb"]), "shape": [2, 64, 64, 3000]}}),
        lambda: dumps({**valid, "rgb": {**pack_array(valid["rgb"]), "shape": [1 << 24, 1 << 24, 3, 3]}}),
        lambda: dumps({**valid, "rgb": {**pack_array(valid["rgb"]), "dtype": "|O"}}),
        lambda: dumps({**valid, "rgb": {"__ndarray__": True, "dtype": "|u1", "shape": [-1], "data": b""}}),
        lambda: dumps({**valid, "state": np.full((2, 4), np.inf)}),
        lambda: msgpack.packb([[[[[[1]]]]]] * 3),
        lambda: msgpack.packb(["plan", 1, 2]),
        lambda: b"\xc1" + good[1:],
        lambda: msgpack.packb({"type": "plan", "id": 1, "rgb": msgpack.ExtType(1, b"\x80\x04K\x01.")}),
        lambda: "a text frame",
        lambda: dumps({**valid, "rgb": np.zeros((2, 2000, 2000, 1), np.uint8)[..., [0, 0, 0]][:, :4]}),
    ]
    return [makers[i % len(makers)]() for i in range(n)]


def test_a_thousand_hostile_messages_each_get_one_error_and_the_server_stays_up(served, ingested: Path) -> None:
    _, url, token, _, proc = served
    obs = episode_observation(ingested)
    valid = {"type": "plan", "id": 1, "task": obs.task, "rgb": obs.rgb, "affordance": obs.affordance,
             "state": obs.state, "command": obs.command}
    with connect(url, max_size=None) as ws:
        ws.send(dumps({"type": "hello", "protocol": 1, "token": token}))
        assert loads(ws.recv(timeout=10))["type"] == "ready"
        for msg in hostile_messages(valid, 1000, np.random.default_rng(0)):
            ws.send(msg)
            reply = loads(ws.recv(timeout=10))
            assert reply["type"] == "error" and isinstance(reply["error"], str) and "\n" not in reply["error"]
            assert set(reply) <= {"type", "id", "error"}
        ws.send(dumps(valid))  # and after all that, a plan
        assert loads(ws.recv(timeout=10))["waypoints"].shape == (16, 3)
    assert proc.poll() is None


def test_a_wrong_token_is_refused_and_the_connection_closed(served) -> None:
    _, url, _, _, proc = served
    with pytest.raises(ServerError, match="wrong or missing token"):
        PolicyClient(url, token="guess")
    with pytest.raises(ServerError, match="wrong or missing token"):
        PolicyClient(url)
    assert proc.poll() is None


def test_a_client_gone_mid_plan_leaves_the_server_serving(served, ingested: Path) -> None:
    _, url, token, _, proc = served
    obs = episode_observation(ingested)
    valid = {"type": "plan", "id": 1, "task": obs.task, "rgb": obs.rgb, "affordance": obs.affordance,
             "state": obs.state, "command": obs.command}
    for _ in range(5):
        with connect(url) as ws:
            ws.send(dumps({"type": "hello", "protocol": 1, "token": token}))
            ws.recv(timeout=10)
            ws.send(dumps(valid))  # and gone before the reply
    with PolicyClient(url, token=token) as client:
        assert client.plan(task=obs.task, rgb=obs.rgb, affordance=obs.affordance, state=obs.state,
                           command=obs.command)["waypoints"].shape == (16, 3)
    assert proc.poll() is None


def test_ctrl_c_stops_a_serving_server_cleanly(closed_loop_model, ingested: Path, tmp_path: Path) -> None:
    proc, url = start_server(closed_loop_model[1], tmp_path)
    obs = episode_observation(ingested)
    with PolicyClient(url) as client:
        client.plan(task=obs.task, rgb=obs.rgb, affordance=obs.affordance, state=obs.state, command=obs.command)
        code, err = stop(proc)
    assert code == 0 and "Traceback" not in err and "stopped after 1 plan(s)" in err
    assert f"on {url}" in err  # the server says it bound 127.0.0.1 (this machine only) without --host


def test_serve_refuses_a_bad_model_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "model.pt"
    bad.write_bytes(b"not a checkpoint")
    assert "model.pt: not a loadable adlpipe checkpoint" in one_line_error(run_module("serve", bad, "--port", "0"))


def test_the_ros_bridge_plans_from_a_real_bags_messages(served, mcap_bags: list[Path]) -> None:
    """The ROS 2 node's core fed a recorded bag's own messages in order (camera, depth, tf, joints, command, task,
    affordance), asking for a plan at every camera frame after the second: each plan starts from the bag's command
    then, and its times follow the frame's stamp."""
    from adlpipe.bags.reader import BagSource
    from adlpipe.bags.topics import TopicMap
    from adlpipe.deploy.ros_bridge import PlanBridge

    _, url, token, _, _ = served
    tm = TopicMap()
    src = BagSource(mcap_bags[0])
    topics = [tm.image, tm.depth, tm.affordance, tm.task, tm.tf, tm.tf_static, tm.joints, tm.action]
    plans = 0
    with PolicyClient(url, token=token) as client:
        bridge = PlanBridge(tm, client.policy)
        for topic, t_ns, decode in src.messages([t for t in topics if t in src.topics()]):
            msg = decode()
            bridge.on_message(topic, t_ns / 1e9, msg)
            if topic == tm.image:
                request = bridge.request()
                if request is None:  # until two frames have a tcp beside them
                    assert plans == 0
                    continue
                assert request["rgb"].shape == (2, 64, 64, 3) and request["state"].shape == (2, 4)
                waypoints, stamps = bridge.path(client.plan(**request))
                assert waypoints.shape == (16, 3)
                assert np.abs(waypoints[0] - bridge.command).max() < 0.3
                assert stamps[0] == pytest.approx(bridge.plan_stamp + 0.1)
                plans += 1
    assert plans >= 5 and bridge.task == "cover the food"


def test_closed_loop_through_the_server_is_closed_loop_in_process(served, closed_loop_model, ingested: Path,
                                                                   tmp_path: Path) -> None:
    """The MuJoCo executor as a client of a real server gives the in-process rollouts plan for plan (each trial's
    /adl/plan messages equal) and outcome for outcome; every rollout is a trial bag that ingest keeps and trials
    decides from (two latencies as two policies, alternating)."""
    from adlpipe.bags.reader import BagSource

    split, model = closed_loop_model
    _, url, token, _, _ = served
    (tmp_path / "token").write_text(token)
    common = ["--models", model, "--closed-loop", "8", "--fm-steps", "1", "--data", ingested, "--split", split,
              "--latency", "0", "300", "--workers", "2"]
    runs = {}
    for name, extra in (("local", []), ("served", ["--server", url, "--token-file", tmp_path / "token"])):
        run_module("replay", *common, *extra, "--trial-bags", tmp_path / name, "--metrics", tmp_path / f"{name}.json",
                   "--details", tmp_path / f"{name}_d.json", "--table", tmp_path / f"{name}.md", check=True)
        runs[name] = json.loads((tmp_path / f"{name}_d.json").read_text())
    assert runs["local"]["per_episode"] == runs["served"]["per_episode"]
    local, served_bags = sorted((tmp_path / "local").glob("*.mcap")), sorted((tmp_path / "served").glob("*.mcap"))
    assert [p.name for p in local] == [p.name for p in served_bags] and len(local) == 6

    def plans(bag: Path) -> np.ndarray:
        return np.array([[[p.pose.position.x, p.pose.position.y, p.pose.position.z] for p in m().poses]
                         for _, _, m in BagSource(bag).messages(["/adl/plan"])])

    for a, b in zip(local, served_bags, strict=True):
        pa, pb = plans(a), plans(b)
        assert pa.shape[1:] == (16, 3) and len(pa) >= 3
        np.testing.assert_array_equal(pa, pb)
    # every trial a bag: ingest keeps it as data, trials decides from the outcomes replay scored
    run_module("ingest", served_bags[0], "-o", tmp_path / "trials.h5", "--size", "64", check=True)
    with h5py.File(tmp_path / "trials.h5") as f:
        (name,) = schema.episode_names(f)
        assert f[schema.EPISODES][name]["frames/rgb"].shape[0] >= 10
    out = run_module("trials", *served_bags, "-o", tmp_path / "decision.json", check=True).stdout
    trials = [line for line in out.splitlines() if line.startswith("trial ")]
    labels = [line.split(" (")[1].split(":")[0] for line in trials]
    assert labels == ["fm/euler-1/Ta-8/lat-0ms", "fm/euler-1/Ta-8/lat-300ms-sync"] * 3
    outcomes = [("success" in line.split(": ")[1]) for line in trials]
    per = runs["served"]["per_episode"]
    scenes = sorted(per["fm/euler-1/Ta-8/lat-0ms"])
    assert outcomes == [per[label][scenes[i // 2]] for i, label in enumerate(labels)]
    assert json.loads((tmp_path / "decision.json").read_text())["trials"] == 6


def test_latency_costs_a_holding_arm_what_an_async_arm_keeps(closed_loop_model, ingested: Path,
                                                               tmp_path: Path) -> None:
    """The oracle's own plans with the world going on for 300 ms per plan: an arm that goes on with the previous
    plan meanwhile (async) ends where it ends without latency; one that holds (sync) runs out of time behind."""
    split, model = closed_loop_model
    run_module("replay", "--models", model, "--closed-loop", "8", "--oracle", "command", "--latency", "0", "300",
               "--execution", "sync", "async", "--data", ingested, "--split", split, "--workers", "2",
               "--metrics", tmp_path / "m.json", "--details", tmp_path / "d.json", "--table", tmp_path / "t.md",
               check=True)
    diag = json.loads((tmp_path / "d.json").read_text())["diagnostics"]
    end = {k.rsplit("/", 1)[1]: [d["end_error_cm"] for d in v.values()] for k, v in diag.items()
           if k.startswith("oracle")}
    plans = {k.rsplit("/", 1)[1]: [d["plans"] for d in v.values()] for k, v in diag.items() if k.startswith("oracle")}
    assert end["lat-300ms-async"] == end["lat-0ms"]
    assert max(end["lat-0ms"]) < 1.0 and sum(end["lat-300ms-sync"]) > sum(end["lat-0ms"]) + 1.0
    assert all(a < b for a, b in zip(plans["lat-300ms-sync"], plans["lat-0ms"], strict=True))


def test_the_example_plans_with_the_public_api(closed_loop_model, ingested: Path) -> None:
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "03_plan_one_observation.py"),
                           str(closed_loop_model[1]), str(ingested)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr
    assert "16 waypoints" in proc.stdout


def test_the_robot_client_example_plans_through_the_server(served, tmp_path: Path) -> None:
    """examples/06_robot_client.py: a robot's loop against a running `adlpipe serve`, with its token."""
    _, url, token, _, _ = served
    (tmp_path / "token").write_text(token + "\n")
    proc = subprocess.run([sys.executable, str(REPO / "examples" / "06_robot_client.py"), url, "--token-file",
                           str(tmp_path / "token"), "--plans", "2"], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, proc.stderr
    assert "serving fm_cnn" in proc.stdout and proc.stdout.count("plan: ") == 2


def test_the_latency_table_pairs_each_row_with_no_latency_on_the_same_scenes() -> None:
    from adlpipe.evaluation.latency import latency_lines, latency_rows

    scenes = [f"s{i}" for i in range(10)]
    base = {s: i < 6 for i, s in enumerate(scenes)}  # 6 of 10
    slow = {s: i < 2 for i, s in enumerate(scenes)}  # 2 of 10: the 4 lost are discordant one way
    details = {"per_episode": {"fm_cnn/euler-1/Ta-8/lat-0ms": base, "fm_cnn/euler-1/Ta-8/lat-160ms-sync": slow},
               "diagnostics": {"fm_cnn/euler-1/Ta-8/lat-160ms-sync": {"s0": {"peak_force_n": 25.0}}}}
    rows = latency_rows(details)
    assert rows[("0ms", "-")]["FM-1"] == "60 [31, 83]; 0 over 20 N"
    assert rows[("160ms", "sync")]["FM-1"] == "20 [6, 51] (-40.0, p = 0.12); 1 over 20 N"
    lines = latency_lines(details, None)
    assert lines[2].startswith("| 0 ms | - |") and lines[3].startswith("| 160 ms | holds its last command |")


def test_eight_robots_at_once_are_each_served_their_own_plans(served, ingested: Path) -> None:
    """8 clients, each its own connection and seed, 20 plans each at once: every reply answers its own request,
    and a client's plans are the ones it would get alone (the server keeps each session's noise apart)."""
    import threading

    _, url, token, log, proc = served
    obs = episode_observation(ingested)
    req = {"task": obs.task, "rgb": obs.rgb, "affordance": obs.affordance, "state": obs.state, "command": obs.command}
    got: dict[int, list[np.ndarray]] = {}
    errors: list[str] = []

    def robot(i: int) -> None:
        try:
            with PolicyClient(url, token=token, seed=100 + i) as c:
                got[i] = [c.plan(**req)["waypoints"] for _ in range(20)]
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(repr(exc))

    threads = [threading.Thread(target=robot, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors and sorted(got) == list(range(8)) and all(len(v) == 20 for v in got.values())
    with PolicyClient(url, token=token, seed=103) as alone:  # robot 3's session again, on its own
        again = [alone.plan(**req)["waypoints"] for _ in range(20)]
    for a, b in zip(again, got[3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(got[3][0], got[4][0])
    assert proc.poll() is None
