"""netsim's vectorised routing against straightforward references.

RadioMedium decides receptions in batches (every receiver of a transmission at once, the
broadcasts of a whole advance() together) and handles the carrier-sense deferrals between
two ends together; Simulation keeps its per-pair counters as arrays and builds the link
table over all pairs at once. Here each is compared with a per-event, per-receiver, per-pair
reference written the plain way, on scripted cases where randomness cannot tell them apart
(backoff windows of one slot, no jitter, no shadowing, a deterministic judge).
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections import deque

import numpy as np
import pytest

from netsim import sim as S
from netsim.channel import DROP_REASONS, REASON_CODE, Jammer, LogDistance, Outcome, RadioMedium, TxFrame
from netsim.faults import FaultState
from netsim.sim import Simulation
from swarmloc.experiment import scenario as SC
from swarmloc.experiment.faults import Cut, Loss, Partition, RadioOff
from swarmloc.node import RadioRx, RadioTx

SINR_OK_DB = 8.0


class Scripted(LogDistance):
    """LogDistance whose verdict is a threshold on SINR instead of a PER draw, so that the
    order in which two implementations draw random numbers cannot change any outcome."""

    def judge(self, distance_m, signal_dbm, interference_tx_mw, interference_all_mw, half_duplex, bits, rng):
        sinr_db = signal_dbm - 10.0 * np.log10(self._noise_mw + interference_all_mw)
        jam_free_db = signal_dbm - 10.0 * np.log10(self._noise_mw + interference_tx_mw)
        far = signal_dbm < self.effective_sensitivity_dbm
        lost = np.where(jam_free_db < SINR_OK_DB, REASON_CODE["collision"], REASON_CODE["jammed"])
        code = np.where(far, REASON_CODE["distance"],
                        np.where(half_duplex, REASON_CODE["half-duplex"], np.where(sinr_db < SINR_OK_DB, lost, 0)))
        return code.astype(np.int8), sinr_db


def scripted(**kw) -> Scripted:
    base = dict(shadowing_sigma_db=0.0, processing_jitter_s=0.0, cw_min=0, cw_max=0, carrier_sense_dbm=-75.0)
    return Scripted(**{**base, **kw})


class ReferenceMedium:
    """The medium one event and one receiver at a time (netsim's RadioMedium before it was
    vectorised), with the deterministic parts of the model only: attempts at equal times in
    the order their senders first offered, as RadioMedium does."""

    def __init__(self, model: Scripted):
        self.m = model
        self.pos: dict[int, np.ndarray] = {}
        self.jammers: tuple[Jammer, ...] = ()
        self.senders: dict[int, dict] = {}
        self.events: list = []
        self.pending: list = []
        self.txs: list[dict] = []
        self.on_air: list[dict] = []
        self.seq = itertools.count()
        self.now = -math.inf

    def set_positions(self, positions):
        self.pos = {k: np.pad(np.asarray(v, float), (0, 3 - len(v))) for k, v in positions.items()}

    def set_jammers(self, jammers):
        self.jammers = tuple(jammers)

    def offer(self, frame: TxFrame, t: float) -> list[Outcome]:
        t = max(t, self.now)
        s = self.senders.setdefault(frame.src, {"order": len(self.senders), "queue": deque(), "current": None,
                                                "retry": 0})
        if s["current"] is None:
            s["current"], s["retry"] = frame, 0
            self.push(t, 1, frame.src)
            return []
        if len(s["queue"]) >= self.m.queue_size:
            return [Outcome(frame.uid, frame.src, r, False, t, "queue", math.nan) for r in self.receivers(frame)]
        s["queue"].append(frame)
        return []

    def push(self, t, kind, payload):
        order = self.senders[payload]["order"] if kind == 1 else next(self.seq)
        heapq.heappush(self.events, (t, kind, order, next(self.seq), payload))

    def receivers(self, frame):
        return [frame.dst] if frame.dst is not None else sorted(n for n in self.pos if n != frame.src)

    def advance(self, t: float) -> list[Outcome]:
        while self.events and self.events[0][0] <= t:
            time, kind, _, _, payload = heapq.heappop(self.events)
            self.now = max(self.now, time)
            self.end(payload, time) if kind == 0 else self.attempt(payload, time)
        self.now = max(self.now, t)
        out = []
        while self.pending and self.pending[0][0] <= t:
            out.append(heapq.heappop(self.pending)[2])
        return out

    def power(self, frm, to, src=None, dst=None) -> float:
        return float(self.m.rx_power_dbm(np.array([np.linalg.norm(frm - to)]), np.zeros(1))[0])

    def attempt(self, src, t):
        s = self.senders[src]
        frame = s["current"]
        pos = self.pos.get(src)
        if pos is None:
            self.report([Outcome(frame.uid, src, r, False, t, "distance", math.nan) for r in self.receivers(frame)])
            return self.finish(src, t)
        cca = self.m.cca_threshold_dbm
        heard = [x["end"] for x in self.on_air
                 if cca is not None and x["src"] != src and self.power(x["pos"], pos) >= cca]
        if heard:
            return self.push(max(heard) + self.m.difs_s, 1, src)
        tx = {"frame": frame, "src": src, "start": t, "end": t + self.m.airtime_s(frame.size), "pos": pos.copy()}
        self.txs.append(tx)
        self.on_air.append(tx)
        heapq.heappush(self.events, (tx["end"], 0, next(self.seq), next(self.seq), tx))

    def end(self, tx, t):
        self.on_air.remove(tx)
        outcomes = self.resolve(tx, t)
        s = self.senders[tx["src"]]
        if tx["frame"].dst is not None and not outcomes[0].delivered and s["retry"] < self.m.unicast_retries:
            s["retry"] += 1
            self.push(t + self.m.difs_s, 1, tx["src"])
        else:
            self.report(outcomes)
            self.finish(tx["src"], t)
        horizon = min([x["start"] for x in self.on_air] + [self.now])
        self.txs = [x for x in self.txs if x["end"] > horizon]

    def finish(self, src, t):
        s = self.senders[src]
        s["current"] = s["queue"].popleft() if s["queue"] else None
        s["retry"] = 0
        if s["current"] is not None:
            self.push(t + (self.m.difs_s if self.m.cca_threshold_dbm is not None else 0.0), 1, src)

    def report(self, outcomes):
        for o in outcomes:
            heapq.heappush(self.pending, (o.t, next(self.seq), o))

    def resolve(self, tx, t) -> list[Outcome]:
        frame = tx["frame"]
        out = []
        overlapping = [x for x in self.txs if x is not tx and x["start"] < tx["end"] and x["end"] > tx["start"]]
        for r in self.receivers(frame):
            if r not in self.pos:
                out.append(Outcome(frame.uid, frame.src, r, False, t, "distance", math.nan))
                continue
            i_tx, i_all = self.interference(tx, overlapping, self.pos[r])
            d = float(np.linalg.norm(self.pos[r] - tx["pos"]))
            code, sinr = self.m.judge(np.array([d]), np.array([self.power(tx["pos"], self.pos[r])]),
                                      np.array([i_tx]), np.array([i_all]),
                                      np.array([r in {x["src"] for x in overlapping}]), np.array([0]), None)
            why = (None, *DROP_REASONS)[int(code[0])]
            arrival = t + d / 299_792_458.0 + self.m.processing_delay_s if why is None else t
            out.append(Outcome(frame.uid, frame.src, r, why is None, arrival, why, float(sinr[0])))
        return out

    def interference(self, tx, overlapping, rpos) -> tuple[float, float]:
        jams = [j for j in self.jammers if j.active_during(tx["start"], tx["end"])]
        edges = {tx["start"], tx["end"]}
        for x in overlapping:
            edges.update((max(x["start"], tx["start"]), min(x["end"], tx["end"])))
        for j in jams:
            edges.update((max(j.t_start, tx["start"]), min(j.t_end, tx["end"])))
        e = sorted(edges)
        worst_tx = worst_all = 0.0
        for lo, hi in zip(e[:-1], e[1:]):
            if hi <= lo:
                continue
            mid = 0.5 * (lo + hi)
            from_tx = sum(10 ** (self.power(x["pos"], rpos) / 10) for x in overlapping if x["start"] <= mid < x["end"])
            from_jam = sum(10 ** (float(self.m.jammer_rx_power_dbm(j, np.array([np.linalg.norm(rpos - j.position)]))[0])
                                  / 10) for j in jams if j.t_start <= mid < j.t_end)
            worst_tx, worst_all = max(worst_tx, from_tx), max(worst_all, from_tx + from_jam)
        return worst_tx, worst_all


def _script(n: int, seed: int, moves: bool, side_m: float):
    """Random nodes in a square, bursts of simultaneous and staggered broadcasts and unicasts
    (some to a node that is not there), a jammer, and a move in the middle."""
    rng = np.random.default_rng(seed)
    pos = {i: rng.uniform(0, side_m, 2) for i in range(n)}
    steps = [("pos", pos), ("jam", [Jammer((350.0, 350.0), 0.0, 0.02, 0.03)])]
    uid = itertools.count(1)
    for burst in range(6):
        t0 = 0.01 * burst
        for src in rng.permutation(n).tolist():
            dst = None if rng.random() < 0.7 else int(rng.choice([d for d in range(n + 1) if d != src]))
            t = t0 if rng.random() < 0.6 else t0 + float(rng.uniform(0, 4e-3))
            steps.append(("offer", TxFrame(next(uid), src, dst, int(rng.integers(0, 120))), t))
        steps.append(("advance", t0 + float(rng.uniform(2e-3, 9e-3))))
        if moves and burst == 2:
            steps.append(("pos", {i: p + rng.normal(0, 30, 2) for i, p in pos.items() if i != 0}))
    steps.append(("advance", 10.0))
    return steps


def _play(medium, steps) -> list[list[tuple]]:
    rounds, out = [], []
    for step in steps:
        if step[0] == "pos":
            medium.set_positions(step[1])
        elif step[0] == "jam":
            medium.set_jammers(step[1])
        elif step[0] == "offer":
            out += medium.offer(step[1], step[2])
        else:
            out += medium.advance(step[1])
            rounds.append(sorted((o.uid, o.receiver, o.delivered, o.reason, o.t, o.sinr_db) for o in out))
            out = []
    return rounds


@pytest.mark.parametrize("seed", range(10))
@pytest.mark.parametrize(("moves", "side_m"), [(False, 150.0), (False, 700.0), (True, 300.0)])
def test_batched_medium_equals_per_event_reference(seed: int, moves: bool, side_m: float) -> None:
    model = scripted()
    steps = _script(12, seed, moves, side_m)
    got = _play(RadioMedium(model, np.random.default_rng(0)), steps)
    want = _play(ReferenceMedium(model), steps)
    assert [len(r) for r in got] == [len(r) for r in want]
    for g, w in zip(got, want):
        for a, b in zip(g, w):
            assert a[:4] == b[:4] and a[4] == pytest.approx(b[4], rel=0, abs=1e-12)
            assert (math.isnan(a[5]) and math.isnan(b[5])) or a[5] == pytest.approx(b[5], abs=1e-9)
    reasons = {r[3] for g in got for r in g}
    assert {None, "collision", "half-duplex", "distance"} <= reasons  # the script exercises them


def test_unicast_retries_follow_the_reference() -> None:
    model = scripted(unicast_retries=2, carrier_sense=False)
    pos = {0: [0.0, 0.0], 1: [100.0, 0.0], 2: [200.0, 0.0]}
    steps = [("pos", pos)] + [("offer", TxFrame(k, k % 2 * 2, 1, 50), 0.001 * (k // 2)) for k in range(12)]
    steps.append(("advance", 5.0))
    got = _play(RadioMedium(model, np.random.default_rng(0)), steps)
    want = _play(ReferenceMedium(model), steps)
    assert [r[:4] for r in got[0]] == [r[:4] for r in want[0]]
    assert np.allclose([r[4:] for r in got[0]], [r[4:] for r in want[0]], rtol=0, atol=1e-12)
    assert {r[3] for r in got[0]} == {"collision"}  # 0 and 2 send to 1 together, retry together, and fail


def test_an_attempt_after_an_end_does_not_sense_what_ended() -> None:
    # Sensing reaches 67 m at -75 dBm. A (x=0) and D (x=50) hear each other; C (x=200) hears
    # neither. A sends at 0; C, hidden, starts during A; D tries after A has ended but while C
    # is on air, and must find the channel free.
    model = scripted()
    steps = [("pos", {0: [0.0, 0.0], 1: [50.0, 0.0], 2: [200.0, 0.0]}),
             ("offer", TxFrame(1, 0, None, 100), 0.0), ("offer", TxFrame(2, 2, None, 200), 0.5e-3),
             ("offer", TxFrame(3, 1, None, 10), 1.5e-3), ("advance", 1.0)]
    got = _play(RadioMedium(model, np.random.default_rng(0)), steps)
    want = _play(ReferenceMedium(model), steps)
    assert [r[:4] for r in got[0]] == [r[:4] for r in want[0]]
    assert np.allclose([r[4] for r in got[0]], [r[4] for r in want[0]], rtol=0, atol=1e-12)
    (d_to_a,) = [r for r in got[0] if r[:2] == (3, 0)]
    assert d_to_a[4] == pytest.approx(1.5e-3 + model.airtime_s(10) + 50.0 / 299_792_458.0 + model.processing_delay_s)


def test_carrier_sense_defers_everyone_who_hears_and_no_one_else() -> None:
    model = scripted(carrier_sense_dbm=-80.0)
    med = RadioMedium(model, np.random.default_rng(3))
    # 0 and 1 hear each other; 2 is hidden from both (>= 400 m) but hears 3.
    med.set_positions({0: [0.0, 0.0], 1: [50.0, 0.0], 2: [600.0, 0.0], 3: [650.0, 0.0]})
    for src in range(4):
        med.offer(TxFrame(src + 1, src, None, 100), 1.0)
    med.advance(1.0)
    starts = sorted((x.src, x.start) for x in med._txs)
    assert starts == [(0, 1.0), (2, 1.0)]  # the first of each group; 1 and 3 defer
    assert med._try_at[1] > 1.0 + model.airtime_s(100) and med._try_at[3] > 1.0 + model.airtime_s(100)
    out = med.advance(5.0)
    assert len({o.uid for o in out}) == 4


# --------------------------------------------------------------------------- #
# Simulation: overlay, counters and the link table over all pairs
# --------------------------------------------------------------------------- #
def _sim(radio: dict, faults: list[dict] = ()) -> Simulation:
    return Simulation(SC.load("random7").with_overrides(radio=radio, faults=list(faults)))


def _reference_links(sim: Simulation) -> list[dict]:
    """link_table as it was computed before: one pair at a time from link_state and the log."""
    delivered, attempts, heard, sinr = {}, {}, {}, {}
    for k, src, rcv, size, why in sim.radio_log:
        attempts[(src, rcv)] = attempts.get((src, rcv), 0) + 1
        delivered[(src, rcv)] = delivered.get((src, rcv), 0) + (why == "")
    heard, sinr = sim.last_heard, sim.last_sinr
    rows = []
    for i, a in enumerate(sim.ids):
        for b in sim.ids[i + 1:]:
            info = sim.medium.link(a, b)
            up_ab, dist, why_ab = sim.link_state(a, b)
            up_ba, _, why_ba = sim.link_state(b, a)
            dlv = delivered.get((a, b), 0) + delivered.get((b, a), 0)
            total = attempts.get((a, b), 0) + attempts.get((b, a), 0)
            h = [heard[d] for d in ((a, b), (b, a)) if d in heard]
            q = [sinr[d] for d in ((a, b), (b, a)) if d in sinr]
            rows.append({"a": a, "b": b, "up": up_ab and up_ba, "distance": dist, "reason": why_ab or why_ba,
                         "snr_db": float(info.snr_db), "sinr_db": min(q) if q else None, "pdr_model": float(info.pdr),
                         "delivered": dlv, "dropped": total - dlv, "delivery_ratio": dlv / total if total else None,
                         "last_heard": max(h) if h else None})
    return rows


def _same_rows(got: list[dict], want: list[dict]) -> None:
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g.keys() == w.keys()
        for key in g:
            if isinstance(w[key], float) and isinstance(g[key], float):
                assert (math.isnan(g[key]) and math.isnan(w[key])) or g[key] == pytest.approx(w[key], rel=1e-12), key
            else:
                assert g[key] == w[key], (key, g, w)


@pytest.mark.parametrize("radio", [{"model": "log-distance"}, {"model": "unit-disk", "range_m": 80.0}])
def test_link_table_equals_per_pair_computation(radio: dict) -> None:
    faults = [{"at": 0.5, "action": "cut", "link": [1, 2], "direction": "forward"},
              {"at": 1.0, "action": "partition", "groups": [[3, 4]]},
              {"at": 1.0, "action": "loss", "probability": 0.5, "node": 5},
              {"at": 1.5, "action": "radio-off", "node": 6},
              {"at": 1.5, "action": "jammer", "name": "j", "position": [0.0, 0.0], "power_dbm": 10.0,
               "radius_m": 30.0}]
    sim = _sim(radio, faults)
    _same_rows(sim.link_table(), _reference_links(sim))  # before tick 0
    for k in range(6):
        sim.tick()
        if k == 3:
            sim.down.add(7)
        sim.exchange([RadioTx(a, None, k, bytes(40)) for a in sim.ids] + [RadioTx(1, 2, 100 + k, bytes(10))])
        _same_rows(sim.link_table(), _reference_links(sim))
    reasons = {why for *_, why in sim.radio_log}
    assert {"", "fault", "partition", "radio-off", "down"} <= reasons
    assert len(sim.radio_arrays()["link_k"]) == 6 * 21  # per tick and pair
    if radio["model"] == "unit-disk":
        assert "jammed" in reasons


def test_fault_matrices_equal_the_per_pair_questions() -> None:
    ids = [1, 2, 3, 4, 5, 6]
    fs = FaultState(ids)
    script = [Cut(link=(1, 2), direction="forward"), Partition(groups=[[3, 4], [5]]), RadioOff(node=6),
              Cut(link=(4, 3)), Loss(probability=0.3, node=2), Loss(probability=0.5, link=(1, 5)),
              Loss(probability=0.2)]
    for k, f in enumerate(script):
        fs.apply(f, float(k), k, "scenario")
        blocked, loss = fs.blocked_matrix(), fs.loss_matrix()
        for i, a in enumerate(ids):
            for j, b in enumerate(ids):
                assert (None, "radio-off", "fault", "partition")[blocked[i, j]] == fs.blocked(a, b)
                assert loss[i, j] == pytest.approx(fs.extra_loss(a, b), abs=1e-15)


def test_log_distance_verdicts_equal_per_reception_rule() -> None:
    m = LogDistance()
    rng = np.random.default_rng(4)
    k = 4000
    d = rng.uniform(10, 900, k)
    signal = m.rx_power_dbm(d, rng.normal(0, 4, k))
    i_tx = np.where(rng.random(k) < 0.3, 10 ** (rng.uniform(-100, -60, k) / 10), 0.0)
    i_all = i_tx + np.where(rng.random(k) < 0.2, 10 ** (rng.uniform(-100, -60, k) / 10), 0.0)
    hd = rng.random(k) < 0.05
    bits = rng.integers(200, 2000, k)
    code, sinr_db = m.judge(d, signal, i_tx, i_all, hd, bits, np.random.default_rng(9))
    u_all = iter(np.random.default_rng(9).random(int(np.sum((signal >= m.effective_sensitivity_dbm) & ~hd))))
    noise = 10 ** (m.noise_floor_dbm / 10)
    for n in range(k):  # the rule of LogDistance.decide before it was vectorised, one reception at a time
        s = 10 ** (signal[n] / 10)
        assert sinr_db[n] == pytest.approx(10 * math.log10(s / (noise + i_all[n])), abs=1e-9)
        if signal[n] < m.effective_sensitivity_dbm:
            want = "distance"
        elif hd[n]:
            want = "half-duplex"
        else:
            u = next(u_all)
            p_all, p_tx, p_snr = (float(m.per(10 * math.log10(s / (noise + i)), bits[n]))
                                  for i in (i_all[n], i_tx[n], 0.0))
            want = None if u >= p_all else "jammed" if u >= p_tx else "collision" if u >= p_snr else "sinr"
        assert (None, *DROP_REASONS)[code[n]] == want
    assert {(None, *DROP_REASONS)[c] for c in code} == {None, "distance", "half-duplex", "sinr", "collision", "jammed"}


def test_fast_deliveries_are_radio_rx() -> None:
    frames = [(b"abc", 3, 7, False), (b"", 4, 8, True)]
    got = S._make_rx([1, 2], [0.5, 0.25], frames, [0, 1])
    assert got == [RadioRx(1, 0.5, b"abc", None, 3, 7, False), RadioRx(2, 0.25, b"", None, 4, 8, True)]
    assert hash(got[0]) == hash(RadioRx(1, 0.5, b"abc", None, 3, 7, False)) and S._DIRECT_RX
    with pytest.raises(AttributeError):
        got[0].t = 1.0  # still frozen


def test_same_seed_same_run_bit_for_bit_and_consistent_summaries() -> None:
    def run() -> Simulation:
        sim = _sim({"model": "log-distance", "queue_size": 1}, [{"at": 1.0, "action": "loss", "probability": 0.3}])
        for k in range(8):
            sim.tick()
            frames = [RadioTx(a, None, 3 * k, bytes(60)) for a in sim.ids]
            frames += [RadioTx(a, a % 7 + 1, 3 * k + s, bytes(30)) for a in sim.ids for s in (1, 2)]  # one overflows
            sim.exchange(frames[::-1])
        return sim

    a, b = run(), run()
    ra, rb = a.radio_arrays(), b.radio_arrays()
    assert ra.keys() == rb.keys()
    for key in ra:
        assert ra[key].dtype == rb[key].dtype and np.array_equal(ra[key], rb[key]), key
    assert {k: v.dtype.str for k, v in ra.items()} == {
        "k": "<i8", "src": "<i8", "receiver": "<i8", "size": "<i8", "delivered": "|b1", "reason": "<U16",
        "link_k": "<i8", "link_t": "<f8", "link_a": "<i8", "link_b": "<i8", "link_snr_db": "<f8", "link_up": "|b1",
        "link_delivered": "<i8", "link_dropped": "<i8", "fault_t": "<f8", "fault_k": "<i8", "fault_action": "<U16",
        "fault_source": "<U16"}
    summary = a.radio_summary()
    assert summary == b.radio_summary()
    assert summary["delivered"] == int(ra["delivered"].sum()) == sum(a.delivered.values())
    reasons, counts = np.unique(ra["reason"][~ra["delivered"]], return_counts=True)
    assert summary["dropped"] == dict(zip(reasons.tolist(), counts.tolist()))
    assert {"loss", "queue"} <= summary["dropped"].keys()
    assert sum(a.attempts.values()) == len(a.radio_log) == len(ra["k"])
    assert list(a.radio_log)[:3] == [tuple(ra[c][i].item() for c in ("k", "src", "receiver", "size", "reason"))
                                     for i in range(3)]


def test_array_and_object_interfaces_give_the_same_outcomes() -> None:
    def play(arrays: bool) -> list[tuple]:
        med = RadioMedium(LogDistance(), np.random.default_rng(11))
        rng = np.random.default_rng(1)
        med.set_positions({i: rng.uniform(0, 500, 2) for i in range(10)})
        out = []
        for k in range(60):
            frame = TxFrame(k, k % 10, None if k % 4 else (k + 3) % 10, 80)
            if arrays:
                drops = med.offer_arrays(frame, 0.0005 * k)
                out += drops.to_list() if drops is not None else []
                out += med.advance_arrays(0.0005 * k + 0.0003).to_list()
            else:
                out += med.offer(frame, 0.0005 * k) + med.advance(0.0005 * k + 0.0003)
        return out + (med.run_to_idle().to_list() if arrays else med.advance(10.0))

    objects, arrays = play(False), play(True)
    assert objects == arrays and len(objects) > 300
    assert [o.t for o in objects] == sorted(o.t for o in objects)


def test_batch_deliveries_equal_the_radio_rx_list() -> None:
    def run(batch: bool) -> list:
        sim = _sim({"model": "log-distance"}, [{"at": 1.0, "action": "loss", "probability": 0.3}])
        out = []
        for k in range(4):
            sim.tick()
            frames = [RadioTx(a, None, 2 * k, bytes(60)) for a in sim.ids]
            frames += [RadioTx(a, a % 7 + 1, 2 * k + 1, bytes(30)) for a in sim.ids[:3]]
            for round_ in (frames[:-3], frames):  # a round without unicasts, one with
                got = sim.exchange_batch(round_) if batch else sim.exchange(round_)
                if isinstance(got, S.Deliveries):
                    assert [(r.receiver, r.t, r.data, r.src, r.seq, r.unicast) for r in got] == list(got.raw())
                    assert all(r.nack is None for r in got)
                out.append((type(got).__name__, list(got)))
        return out

    batch, objects = run(True), run(False)
    assert [b for _, b in batch] == [o for _, o in objects]
    assert {kind for kind, _ in batch} == {"Deliveries", "list"} and {kind for kind, _ in objects} == {"list"}
