#!/usr/bin/env python3
"""Replay a dray traffic trace (`dray render --trace-out FILE`) in SimGrid and print the
predicted job time (docs/caches.md "Simulation at scale").

Run it through benches/sim/run.sh, which fetches SimGrid into target/simgrid and sets
PYTHONPATH and LD_LIBRARY_PATH:

    benches/sim/run.sh replay.py TRACE [--nodes N] [--bandwidth 1Gbps] [--latency 100us]

The model, one SimGrid actor per tracing thread of each node (a node stands for a worker):
- every `step` record of the trace is replayed as a computation of its thread CPU
  nanoseconds (1 flop = 1 ns of the recording machine's core; `--speed` scales hosts);
  the process CPU the steps and loads did not account for (gRPC encoding, the reports,
  the coordinator's film) runs on a runtime actor per node beside the tracing threads
  (`--overhead-on runtime`), as the trace's total shared among the steps (`--overhead
  trace`) or modelled from the replay's own counts (`--overhead model`);
- a step of domain d waits until the rays it takes have arrived: the k-th step of d
  starts once the rays sent to d reach the sum of the first k steps' `rays_in` (batch
  dependencies counted in rays, as the worker's queues merge batches); camera steps
  need nothing. Among ready steps a node takes the domain with the most rays waiting
  (the worker's fullest queue), camera steps when none is ready;
- a step's rays out become one message per destination node (the owner of their
  domains: a worker's per-peer outbox), of their bytes, over the platform's links (SimGrid's TCP model, LV08); rays for a
  domain the node owns arrive at once; a node takes messages in as they come (a permanent
  receiver on its mailbox, as a TCP stream does), not one after another;
- a domain's first step on a node loads it first: its bytes from a file-system host
  (`--fs-bandwidth`; reads are free without it, as for the in-memory packages of the
  recording), then its build CPU, plus the recording's `--load-delay-ms`;
- a cache-link message (a `cache` line, trace version 2) goes between its worker's node
  and its cache host's node (the worker that declared the host in a `cache_host` line;
  an undeclared host is a stand-alone one, a host of its own) when the replay ends the
  step of its worker that ended first at or after it; nothing waits for it but the
  job's end (`--no-cache-messages` leaves them out);
- where nodes compute: a host of their own each (one core per tracing thread); with
  `--one-host` alone every node on one host of `--cores` cores, messages looping through
  its link; with `--one-host` and a `--topology`, each node keeps its own host and links
  but computes on one shared host of `--cores` cores (worker processes sharing one
  machine behind emulated links).

With the trace's own worker count (the default) each domain stays where the trace had
it and each step on its worker. With `--nodes N` otherwise, domains are re-dealt round
robin (domain i to node i mod N, as the `domain` schedule deals them) and camera steps in
turn, the CPU per ray kept. Rays a recorded step traced through several domains its worker
owned stay inside one step: at more nodes than the trace had, that traffic is missing,
so record with as many workers as the domains allow.

The job time predicted is the simulated makespan plus the recording's fixed part (wall
time outside the workers' steps: submission, partitioning, the last report), which the
simulation does not model.
"""

import argparse
import json
import math
import re
import sys
from collections import defaultdict


class TraceError(Exception):
    pass


# The trace versions this replay reads: 1, and 2, which added the cache-link messages
# (`cache` and `cache_host` records; worker/src/traffic_trace.rs).
VERSIONS = (1, 2)


def parse_rate(text, unit_name):
    """'1Gbps', '10gbit', '125MBps', '500MB/s' or a number (bytes/s) -> bytes/s."""
    m = re.fullmatch(r"\s*([0-9.]+(?:e[0-9+-]+)?)\s*([kKmMgGtT]?)(bit|bps|Bps|B/s|B)?\s*", text)
    if not m:
        raise SystemExit(f"{unit_name} {text!r}: not a rate (examples: 1Gbps, 10gbit, 500MB/s)")
    v = float(m.group(1))
    scale = {"": 1, "k": 1e3, "m": 1e6, "g": 1e9, "t": 1e12}[m.group(2).lower()]
    unit = m.group(3) or "B"
    bits = unit in ("bit", "bps")
    return v * scale / (8 if bits else 1)


def parse_time(text, name):
    """'100us', '1ms', '10µs', '0.5s' or a number (seconds) -> seconds."""
    m = re.fullmatch(r"\s*([0-9.]+(?:e[0-9+-]+)?)\s*(ns|us|µs|ms|s)?\s*", text)
    if not m:
        raise SystemExit(f"{name} {text!r}: not a time (examples: 10us, 1ms)")
    return float(m.group(1)) * {"ns": 1e-9, "us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1, None: 1}[m.group(2)]


class Trace:
    """A trace file, read and checked."""

    def __init__(self, path):
        self.job = None
        self.workers = {}  # worker id -> threads
        self.steps = []
        self.loads = []
        self.forwards = []
        self.caches = []  # cache-link messages (v2)
        self.cache_hosts = {}  # cache host endpoint -> the worker it runs beside (v2)
        try:
            f = open(path, encoding="utf-8")
        except OSError as e:
            raise TraceError(f"cannot read the trace {path}: {e}") from e
        with f:
            for n, line in enumerate(f, 1):
                if not line.strip():
                    continue
                try:
                    r = json.loads(line)
                except json.JSONDecodeError as e:
                    raise TraceError(f"{path}:{n}: not JSON ({e})") from e
                if r.get("v") not in VERSIONS:
                    raise TraceError(f"{path}:{n}: trace version {r.get('v')!r}, this replay reads {VERSIONS}")
                kind = r.get("rec")
                if kind == "job":
                    self.job = r
                elif kind == "worker":
                    self.workers[r["worker"]] = int(r.get("threads", 1))
                elif kind == "step":
                    self.steps.append(r)
                elif kind == "load":
                    self.loads.append(r)
                elif kind == "forward":
                    self.forwards.append(r)
                elif kind == "cache":
                    self.caches.append(r)
                elif kind == "cache_host":
                    self.cache_hosts[r["host"]] = r["worker"]
                else:
                    raise TraceError(f"{path}:{n}: unknown record {kind!r}")
        if self.job is None:
            raise TraceError(f"{path}: no `job` line (was it written by `dray render --trace-out`?)")
        if not self.workers:
            raise TraceError(f"{path}: no worker wrote records (did the job run on workers?)")
        for s in self.steps + self.loads + self.caches:
            if s["worker"] not in self.workers:
                raise TraceError(f"{path}: a record of worker {s['worker']!r}, which has no `worker` line")

    def totals(self):
        rays_sent = sum(o["rays"] for s in self.steps for o in s["out"] if o["remote"])
        bytes_sent = sum(o["bytes"] for s in self.steps for o in s["out"] if o["remote"])
        return {
            "steps": len(self.steps),
            "rays_traced": sum(s["traced"] for s in self.steps),
            "rays_sent": rays_sent + sum(f["rays"] for f in self.forwards),
            "bytes_sent": bytes_sent + sum(f["bytes"] for f in self.forwards),
            "loads": len(self.loads),
            "step_cpu_s": sum(s["cpu_ns"] for s in self.steps) / 1e9,
            "load_cpu_s": sum(l["cpu_ns"] for l in self.loads) / 1e9,
            "busy_span_s": max((s["t1"] for s in self.steps), default=0) / 1e9,
            "cache_messages": sum(c["msgs"] for c in self.caches),
            "cache_bytes": sum(c["bytes"] for c in self.caches),
        }


class Plan:
    """Who does what in the replay: the owner node of every domain, the node of every
    step, the loads' costs."""

    def __init__(self, trace, nodes, cache_messages=True):
        workers = sorted(trace.workers)
        self.nodes = nodes
        self.same = nodes == len(workers)
        index = {w: i for i, w in enumerate(workers)}
        domains = sorted({s["domain"] for s in trace.steps if s["domain"] is not None}
                         | {o["domain"] for s in trace.steps for o in s["out"]})
        # Where each domain's rays were traced in the trace (most rays in wins).
        traced_at = defaultdict(lambda: defaultdict(int))
        for s in trace.steps:
            if s["domain"] is not None:
                traced_at[s["domain"]][s["worker"]] += s["rays_in"]
        self.owner = {}
        for i, d in enumerate(domains):
            if self.same and traced_at.get(d):
                w = max(traced_at[d].items(), key=lambda kv: (kv[1], kv[0]))[0]
                self.owner[d] = index[w]
            else:
                self.owner[d] = i % nodes
        self.step_node = []
        turn = 0
        for s in trace.steps:
            if s["domain"] is not None:
                self.step_node.append(self.owner[s["domain"]])
            elif self.same:
                self.step_node.append(index[s["worker"]])
            else:
                self.step_node.append(turn % nodes)
                turn += 1
        # A domain's load: the trace's first load of it (bytes, build CPU).
        self.load = {}
        for l in sorted(trace.loads, key=lambda l: l["t0"]):
            self.load.setdefault(l["domain"], (l["bytes"], l["cpu_ns"]))
        self.single = domains[0] if len(domains) == 1 else None
        # A worker's node, for its cache host's messages: its own at the trace's node
        # count; re-dealt, the owner of the domain it traced most rays of (under remote
        # placement a wall's cache host is beside its domain's owner).
        self.worker_node = {}
        for w in workers:
            mine = {d: by[w] for d, by in traced_at.items() if w in by}
            if self.same or not mine:
                self.worker_node[w] = index[w] % nodes
            else:
                self.worker_node[w] = self.owner[max(mine.items(), key=lambda kv: (kv[1], -kv[0]))[0]]
        # Cache hosts no worker declared (stand-alone hosts): a node of their own each,
        # after the workers' nodes.
        self.caches = trace.caches if cache_messages else []
        self.standalone = sorted({c["host"] for c in self.caches} - set(trace.cache_hosts))
        host_node = {h: nodes + i for i, h in enumerate(self.standalone)}
        for h, w in trace.cache_hosts.items():
            host_node[h] = self.worker_node[w]
        # Each cache message goes with the step of its worker that ended first at or
        # after it (sent as that step ends in the replay, so it keeps its place in the
        # worker's work however the replay's times stretch), or at the start if the worker
        # traced no step: (from node, to node, bytes) per step index, or in `cache_first`.
        by_worker = defaultdict(list)
        for k, s in enumerate(trace.steps):
            by_worker[s["worker"]].append((s["t1"], k))
        for v in by_worker.values():
            v.sort()
        self.cache_after = defaultdict(list)
        self.cache_first = []
        import bisect
        for c in self.caches:
            me, peer = self.worker_node[c["worker"]], host_node[c["host"]]
            msg = (me, peer, c["bytes"]) if c["dir"] == "sent" else (peer, me, c["bytes"])
            steps = by_worker.get(c["worker"])
            if not steps:
                self.cache_first.append(msg)
                continue
            j = bisect.bisect_left(steps, (c["t"], -1))
            self.cache_after[steps[min(j, len(steps) - 1)][1]].append(msg)


def simulate(trace, a):
    import simgrid
    from simgrid import Actor, Comm, Engine, LinkInRoute, Mailbox, NetZone, Semaphore, this_actor

    nodes = a.nodes or len(trace.workers)
    plan = Plan(trace, nodes, not a.no_cache_messages)
    threads = a.threads or max(trace.workers.values())
    t = trace.totals()
    stats = trace.job.get("stats", {})
    accounted = t["step_cpu_s"] + t["load_cpu_s"]
    overhead = 0.0
    if a.overhead == "trace" and t["step_cpu_s"] > 0:
        overhead = max(0.0, stats.get("cpu_seconds", accounted) - accounted) / t["step_cpu_s"]
    # The same overhead in ns per unit of each step's weight (its CPU, or the rays it took
    # in and sent away), for `--overhead-on runtime`.
    # `--overhead model`: the same CPU from the run's counts instead of its total, so that a
    # trace re-dealt to other node counts pays what those nodes would: per batch sent to
    # another node, per ray sent, and each process's background share of a core.
    model = a.overhead == "model"
    if model:
        overhead = 0.0
    weight = (lambda s: s["cpu_ns"]) if a.overhead_by == "cpu" else \
        (lambda s: s["rays_in"] + sum(o["rays"] for o in s["out"] if o["remote"]))
    total_weight = sum(weight(s) for s in trace.steps)
    per_weight = overhead * t["step_cpu_s"] * 1e9 / total_weight if total_weight else 0.0
    load_delay = (a.load_delay_ms if a.load_delay_ms is not None else trace.job.get("load_delay_ms", 0)) / 1e3

    e = Engine([sys.argv[0], "--log=root.thresh:critical", "--cfg=contexts/stack-size:256",
                f"--cfg=network/model:{a.network_model}"])
    # `star`: each node has one link (its NIC, each direction) to a switch, as a cluster
    # has; `pairs`: each ordered pair of nodes has a link of its own, as `--emulate-link`
    # shapes every connection separately. `--one-host` alone: every node on the one
    # host, no links (loopback, as `dray render --workers N`); `--one-host` with a
    # topology: each node keeps a host of its own for its links and computes on the
    # shared one (`dray cluster --emulate-link` on one machine: processes sharing its
    # cores, each connection shaped).
    topology = a.topology or ("none" if a.one_host else "star")
    shared_cores = a.one_host and topology != "none"
    pairs = topology == "pairs"
    zone = NetZone.create_full_zone("cluster") if pairs else NetZone.create_star_zone("cluster")
    speed = 1e9 * a.speed
    if model:
        # Each process's background CPU (heartbeats, timers, its runtime's polling) taken
        # off its host's cores as a slower core.
        per_host = nodes if a.one_host else 1
        cores = a.cores if a.one_host else threads
        speed *= 1.0 - min(0.9, per_host * a.process_cpu / cores)
    hosts = []
    # The nodes' hosts, then one per stand-alone cache host (no tracing threads).
    members = nodes + len(plan.standalone)
    host_count = 1 if topology == "none" else members
    for i in range(host_count):
        h = zone.create_host(f"node{i}" if i < nodes else f"cache{i - nodes}", speed)
        h.core_count = a.cores if a.one_host else threads
        # (The one host of `--one-host` alone has its star link too: its nodes' messages
        # to each other loop through it.)
        if not pairs:
            link = zone.create_split_duplex_link(f"nic{i}", a.bandwidth).set_latency(a.latency)
            zone.add_route(h.netpoint, None, None, None, [LinkInRoute(link, LinkInRoute.Direction.UP)], True)
        hosts.append(h)
    if pairs:
        for i, hi in enumerate(hosts):
            for j, hj in enumerate(hosts):
                if i != j:
                    link = zone.create_link(f"link{i}-{j}", a.bandwidth).set_latency(a.latency)
                    zone.add_route(hi.netpoint, hj.netpoint, None, None, [LinkInRoute(link)], False)
    # Where nodes compute: their own hosts, or (`--one-host` with a topology) one host
    # of `--cores` cores that every node's tracing threads, loads and runtime share,
    # reached by no link (SimGrid 3.32's Python `Exec.host` setter, which would move an
    # execution to another host, hangs; the actors live there instead and hand their
    # messages to a sender on their node's host).
    cpu_host = None
    if shared_cores:
        cpu_host = zone.create_host("cores", speed)
        cpu_host.core_count = a.cores
    fs = None
    if a.fs_bandwidth:
        fs = zone.create_host("fs", speed)
        if pairs:
            link = zone.create_link("fs-link", a.fs_bandwidth).set_latency(a.latency)
            for h in hosts:
                zone.add_route(fs.netpoint, h.netpoint, None, None, [LinkInRoute(link)], True)
        else:
            link = zone.create_split_duplex_link("fs-nic", a.fs_bandwidth).set_latency(a.latency)
            zone.add_route(fs.netpoint, None, None, None, [LinkInRoute(link, LinkInRoute.Direction.UP)], True)
    zone.seal()

    dynamic = a.schedule == "dynamic"

    class Node:
        def __init__(self, i):
            self.i = i
            self.host = hosts[0 if topology == "none" else i]  # its links
            self.cpu_host = cpu_host or self.host  # its cores
            self.outbox = []  # messages for the sender (shared cores): (mailbox, payload, bytes)
            self.outbox_sem = Semaphore(0)
            self.domains = []  # the domains this node holds (may trace), in the order given
            self.free = []  # camera and other steps that need no rays, in trace order
            self.free_next = 0
            self.resident = set()
            self.loading = set()
            self.waiting = 0
            self.sem = Semaphore(0)
            self.expected = 0  # messages this node will receive (static schedule)
            self.received = 0
            self.pending = 0.0  # runtime CPU (ns) waiting for the node's runtime thread
            self.executors = threads
            self.runtime_sem = Semaphore(0)

        def wake(self):
            n, self.waiting = self.waiting, 0
            for _ in range(n):
                self.sem.release()

    # A domain's queue is one, whichever of its holders the rays were sent to (with one
    # holder, the static schedules, that is the owner's queue; with replicas, rays sent to
    # one holder may be traced by another: optimistic by the time to forward them).
    ns = [Node(i) for i in range(members)]
    steps_of = defaultdict(list)  # domain -> [step index], in trace order
    next_step = defaultdict(int)
    arrived = defaultdict(int)
    taken = defaultdict(int)
    holders = {d: [ns[o]] for d, o in plan.owner.items()}
    turn = defaultdict(int)  # domain -> the next holder to send to
    for d, o in sorted(plan.owner.items()):
        ns[o].domains.append(d)
    for k, s in enumerate(trace.steps):
        if s["domain"] is None or s["rays_in"] == 0:
            ns[plan.step_node[k]].free.append(k)
        else:
            steps_of[s["domain"]].append(k)
        for dest in {plan.owner[o["domain"]] for o in s["out"]} - {plan.step_node[k]}:
            ns[dest].expected += 1
    # Cache-link messages: each between two nodes (a node's own stay inside it).
    for src, dest, size in plan.cache_first + [m for ms in plan.cache_after.values() for m in ms]:
        if src != dest:
            ns[dest].expected += 1
    incoming = defaultdict(int)
    for s in trace.steps:
        for o in s["out"]:
            incoming[o["domain"]] += o["rays"]
    short = []
    need = {}
    for d, ks in steps_of.items():
        c, cum = 0, []
        for k in ks:
            c += trace.steps[k]["rays_in"]
            cum.append(c)
        if c > incoming[d]:
            short.append((d, c, incoming[d]))
        # A trace whose steps take more rays than were sent (rays made in a cache
        # actor's answer, say) must not stall: the last steps need what arrives.
        need[d] = [min(x, incoming[d]) for x in cum]
    untaken = {"steps": sum(len(ks) for ks in steps_of.values())}
    result = {"finish": 0.0, "steps_done": 0, "rays_in": 0, "messages": 0, "bytes_sent": 0, "rays_sent": 0,
              "replicas": 0, "loads": 0, "cache_messages": 0, "cache_bytes": 0, "cache_local": 0}

    def ready_domain(n):
        """The domain with the most rays waiting whose next step can start, resident
        first; None if there is none."""
        best, best_q, best_res = None, -1, False
        for d in n.domains:
            j = next_step[d]
            if j >= len(steps_of[d]) or arrived[d] < need[d][j]:
                continue
            if d in n.loading:
                continue
            res = d in n.resident
            q = arrived[d] - taken[d]
            if (res, q) > (best_res, best_q):
                best, best_q, best_res = d, q, res
        return best

    def has_work(n):
        """Whether this node may still get a step: its own camera steps, or a step of a
        domain it holds (or, under the dynamic schedule, of any domain)."""
        if n.free_next < len(n.free):
            return True
        if dynamic:
            return untaken["steps"] > 0
        return any(next_step[d] < len(steps_of[d]) for d in n.domains)

    def ensure_loaded(n, d):
        if d is None or d in n.resident:
            return
        n.loading.add(d)
        result["loads"] += 1
        size, cpu = plan.load.get(d, (0, 0))
        if fs is not None and size > 0:
            Comm.sendto(fs, n.host, size)
        if load_delay > 0:
            this_actor.sleep_for(load_delay)
        if cpu > 0:
            this_actor.execute(cpu)
        n.loading.discard(d)
        n.resident.add(d)

    def arrive(d, rays):
        arrived[d] += rays
        for h in holders[d]:
            h.wake()

    def destination(n, d):
        """Where rays for d go: here if this node holds d, else its holders in turn."""
        hs = holders[d]
        if n in hs:
            return n
        turn[d] += 1
        return hs[turn[d] % len(hs)]

    def deliver(n, s):
        # One message per destination node, as a worker's per-peer outbox sends them.
        batches = defaultdict(list)
        for o in s["out"]:
            dest = destination(n, o["domain"])
            if dest is n:
                arrive(o["domain"], o["rays"])
            else:
                batches[dest.i].append(o)
        for i, os_ in batches.items():
            size = sum(o["bytes"] for o in os_)
            result["messages"] += 1
            result["bytes_sent"] += size
            result["rays_sent"] += sum(o["rays"] for o in os_)
            send(n, Mailbox.by_name(f"n{i}"), [(o["domain"], o["rays"]) for o in os_], max(1, size))
        return batches

    def send_cache(msgs):
        """Cache-link messages (from node, to node, bytes), each from its sender's host
        by that node's sender actor; a node's own stay inside it."""
        for src, dest, size in msgs:
            if src == dest:
                result["cache_local"] += 1
                continue
            result["cache_messages"] += 1
            result["cache_bytes"] += size
            m = ns[src]
            m.outbox.append((Mailbox.by_name(f"n{dest}"), None, max(1, size)))
            m.outbox_sem.release()

    def send(n, box, payload, size):
        """A message from node n, sent from its host (its sender's, when n computes on the
        shared host: no simulated time passes in the hand-over)."""
        if n.cpu_host is n.host:
            box.put_init(payload, size).detach()
        else:
            n.outbox.append((box, payload, size))
            n.outbox_sem.release()

    def sender(n):
        # A daemon: the receivers wait for every message, so none is left unsent.
        Actor.self().daemonize()
        for _ in range(len(n.outbox)):
            # Queued before the simulation started (cache messages of a worker with no
            # step), with no release of the semaphore.
            box, payload, size = n.outbox.pop(0)
            box.put_init(payload, size).detach()
        while True:
            n.outbox_sem.acquire()
            box, payload, size = n.outbox.pop(0)
            box.put_init(payload, size).detach()

    def executor(n):
        while True:
            d = ready_domain(n)
            if d is not None:
                k = steps_of[d][next_step[d]]
                next_step[d] += 1
                taken[d] += trace.steps[k]["rays_in"]
                untaken["steps"] -= 1
                if untaken["steps"] == 0 and dynamic:
                    for m in ns:
                        m.wake()
                ensure_loaded(n, d)
            elif n.free_next < len(n.free):
                k = n.free[n.free_next]
                n.free_next += 1
                if plan.single is not None:
                    if plan.single in n.loading:
                        n.free_next -= 1
                        n.waiting += 1
                        n.sem.acquire()
                        continue
                    ensure_loaded(n, plan.single)
            elif has_work(n):
                n.waiting += 1
                n.sem.acquire()
                continue
            else:
                break
            s = trace.steps[k]
            cpu = s["cpu_ns"]
            if a.overhead_on == "thread" and not model:
                cpu += per_weight * weight(s)
            if cpu > 0:
                this_actor.execute(cpu)
            result["steps_done"] += 1
            result["rays_in"] += s["rays_in"]
            batches = deliver(n, s)
            if plan.cache_after.get(k):
                send_cache(plan.cache_after[k])
            # The step's share of the process CPU outside steps (`--overhead`).
            extra = per_weight * weight(s) if a.overhead_on == "runtime" else 0.0
            if model:
                extra = len([o for os_ in batches.values() for o in os_]) * a.batch_cpu_us * 1e3 \
                    + sum(o["rays"] for os_ in batches.values() for o in os_) * a.ray_cpu_us * 1e3
            if extra > 0 and a.overhead_on == "runtime":
                n.pending += extra
                n.runtime_sem.release()
            elif extra > 0:
                this_actor.execute(extra)
            n.wake()
            result["finish"] = max(result["finish"], Engine.clock)
        n.executors -= 1
        n.runtime_sem.release()
        n.wake()

    def runtime(n):
        # The node's runtime thread: the process CPU outside the steps (encoding and
        # decoding batches, the reports, the film), taken as the steps leave it, beside
        # the tracing threads and competing with them for the cores, not in their way.
        while True:
            if n.pending > 0:
                work, n.pending = n.pending, 0.0
                this_actor.execute(work)
                result["finish"] = max(result["finish"], Engine.clock)
            elif n.executors == 0:
                return
            else:
                n.runtime_sem.acquire()

    def receiver(n):
        box = Mailbox.by_name(f"n{n.i}")
        # A permanent receiver: messages flow to the node as they are sent, as on a TCP
        # stream. Without it every message waited for this actor's next get, so the
        # transfers into a node ran one at a time behind their latency: a 0.44 s job
        # replayed on 2 nodes took 0.86 s at 10 us and 7.8 s at 100 us (now 0.34, 0.36).
        box.set_receiver(Actor.self())
        if dynamic:
            # Messages to a node are not known ahead under the dynamic schedule: the
            # receiver lives as long as the simulation (a daemon).
            Actor.self().daemonize()
        while dynamic or n.received < n.expected:
            payload = box.get()
            if payload is None:
                # A cache-link message: the job is not over before it arrives.
                result["finish"] = max(result["finish"], Engine.clock)
            else:
                for d, rays in payload:
                    arrive(d, rays)
            n.received += 1

    def scheduler():
        # Navratil et al. 2012's dynamic schedule, as the coordinator runs it from the
        # workers' queue reports: every round, each node with nothing ready gets the
        # domain with the most rays waiting per holder, loaded on its first step.
        while untaken["steps"] > 0:
            this_actor.sleep_for(a.round_ms / 1e3)
            idle = [m for m in ns if m.waiting > 0 and ready_domain(m) is None and m.free_next >= len(m.free)]
            for m in idle:
                best, best_p = None, a.min_queue
                for d, ks in steps_of.items():
                    if next_step[d] >= len(ks) or m in holders[d]:
                        continue
                    p = (arrived[d] - taken[d]) / len(holders[d])
                    if p > best_p:
                        best, best_p = d, p
                if best is not None:
                    holders[best].append(m)
                    m.domains.append(best)
                    result["replicas"] += 1
                    m.wake()

    for src, dest, size in plan.cache_first:
        if src != dest:
            result["cache_messages"] += 1
            result["cache_bytes"] += size
            ns[src].outbox.append((Mailbox.by_name(f"n{dest}"), None, max(1, size)))
        else:
            result["cache_local"] += 1
    for n in ns:
        if n.expected or dynamic:
            Actor.create(f"recv{n.i}", n.host, receiver, n)
        if n.cpu_host is not n.host or plan.caches:
            Actor.create(f"send{n.i}", n.host, sender, n)
        if n.i >= nodes:
            continue  # a stand-alone cache host: no tracing threads
        for th in range(threads):
            Actor.create(f"node{n.i}.t{th}", n.cpu_host, executor, n)
        if a.overhead_on == "runtime":
            Actor.create(f"node{n.i}.runtime", n.cpu_host, runtime, n)
    if dynamic:
        Actor.create("scheduler", hosts[0], scheduler)
    e.run()
    if result["steps_done"] != len(trace.steps):
        raise TraceError(
            f"the replay stopped with {len(trace.steps) - result['steps_done']} of "
            f"{len(trace.steps)} steps never ready: the trace's rays in and rays out disagree"
            + (f" (domains {short[:5]} take more rays than were sent)" if short else ""))
    fixed = max(0.0, trace.job["wall_ns"] / 1e9 - t["busy_span_s"])
    return {
        "simgrid": simgrid.simgrid_version if hasattr(simgrid, "simgrid_version") else None,
        "nodes": nodes,
        "threads": threads,
        "one_host": a.one_host,
        "cores": a.cores if a.one_host else threads,
        "bandwidth_Bps": a.bandwidth,
        "network_model": a.network_model,
        "topology": topology,
        "shared_cores": shared_cores,
        "latency_s": a.latency,
        "speed": a.speed,
        "cpu_overhead_ratio": overhead,
        "overhead": a.overhead,
        "overhead_on": a.overhead_on,
        "overhead_by": a.overhead_by,
        "makespan_s": result["finish"],
        "fixed_s": fixed,
        "predicted_s": result["finish"] + fixed,
        "measured_s": trace.job["wall_ns"] / 1e9,
        "recorded_workers": len(trace.workers),
        "steps": result["steps_done"],
        "rays_in": result["rays_in"],
        "rays_traced": t["rays_traced"],
        "rays_sent": result["rays_sent"],
        "bytes_sent": result["bytes_sent"],
        "messages": result["messages"],
        "cache_messages": result["cache_messages"],
        "cache_bytes": result["cache_bytes"],
        "cache_local": result["cache_local"],
        "schedule": a.schedule,
        "replicas": result["replicas"],
        "loads": result["loads"],
        "trace": t,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(prog="benches/sim/replay.py", description=__doc__.split("\n\n")[0])
    ap.add_argument("trace", help="a trace from `dray render --trace-out`")
    ap.add_argument("--nodes", type=int, help="nodes to replay on (default: the trace's workers)")
    ap.add_argument("--threads", type=int, help="tracing threads per node (default: the trace's)")
    ap.add_argument("--bandwidth", default="10Gbps", help="each node's link, each way (default 10Gbps)")
    ap.add_argument("--latency", default="10us", help="each link's latency (default 10us)")
    ap.add_argument("--speed", type=float, default=1.0, help="core speed against the recording machine's (default 1)")
    ap.add_argument("--fs-bandwidth", help="a shared file system's link for domain loads (default: loads read nothing)")
    ap.add_argument("--load-delay-ms", type=float, help="added to every load (default: the recording's)")
    ap.add_argument("--one-host", action="store_true",
                    help="every node computes on one host of --cores cores: alone, with no links between "
                         "nodes (validation against `dray render --workers N`); with --topology, each node "
                         "keeps its links (validation against `dray cluster --emulate-link` on one machine)")
    ap.add_argument("--cores", type=int, help="cores of the one host (default: the recording machine's)")
    ap.add_argument("--overhead", choices=["trace", "model", "none"], default="trace",
                    help="the process CPU outside steps and loads: the trace's total spread over the steps "
                         "(default), a model of it from the replay's own counts (--batch-cpu-us, --ray-cpu-us, "
                         "--process-cpu: for traces re-dealt to other node counts), or none")
    ap.add_argument("--batch-cpu-us", type=float, default=9.9,
                    help="--overhead model: CPU per batch of one step's rays for one domain on another node")
    ap.add_argument("--ray-cpu-us", type=float, default=0.44,
                    help="--overhead model: CPU per ray sent to another node (encoding and decoding)")
    ap.add_argument("--process-cpu", type=float, default=0.0117,
                    help="--overhead model: each process's background share of one core")
    ap.add_argument("--overhead-on", choices=["runtime", "thread"], default="runtime",
                    help="where that CPU runs: on a runtime thread of each node beside the tracing threads "
                         "(default), or added to each step on its tracing thread")
    ap.add_argument("--overhead-by", choices=["rays", "cpu"], default="rays",
                    help="how it is shared among steps: by the rays each step took in and sent to other "
                         "nodes (default), or by each step's CPU")
    ap.add_argument("--schedule", choices=["static", "dynamic"], default="static",
                    help="static: each domain on one node (default); dynamic: every --round-ms, a node with "
                         "nothing ready gets a replica of the domain with the most rays waiting per holder "
                         "(Navratil et al. 2012), loaded on its first step")
    ap.add_argument("--round-ms", type=float, default=50.0, help="--schedule dynamic: the scheduler's round")
    ap.add_argument("--min-queue", type=float, default=1000.0,
                    help="--schedule dynamic: rays waiting per holder below which no replica is made")
    ap.add_argument("--network-model", choices=["LV08", "CM02"], default="LV08",
                    help="SimGrid's network model: LV08 (its default, TCP over real links: latency x13.01, "
                         "bandwidth x0.97) or CM02 (a message takes latency + size / bandwidth, as "
                         "`--emulate-link` shapes it)")
    ap.add_argument("--topology", choices=["star", "pairs"],
                    help="star: one link per node to a switch (a cluster's NICs; the default without "
                         "--one-host); pairs: a link per ordered pair of nodes (how `--emulate-link` shapes "
                         "each connection)")
    ap.add_argument("--no-cache-messages", action="store_true",
                    help="leave out the trace's cache-link messages (as a version 1 trace has none)")
    ap.add_argument("--json", action="store_true", help="print the result as JSON")
    a = ap.parse_args(argv)
    a.bandwidth = parse_rate(a.bandwidth, "--bandwidth")
    a.latency = parse_time(a.latency, "--latency")
    if a.fs_bandwidth:
        a.fs_bandwidth = parse_rate(a.fs_bandwidth, "--fs-bandwidth")
    if a.nodes is not None and a.nodes < 1:
        raise SystemExit(f"--nodes {a.nodes}: at least 1")
    if a.bandwidth <= 0 or not math.isfinite(a.bandwidth):
        raise SystemExit("--bandwidth must be above 0")
    try:
        trace = Trace(a.trace)
        if a.cores is None:
            a.cores = int(trace.job.get("cores", 1))
        r = simulate(trace, a)
    except TraceError as e:
        print(f"replay: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(r))
    else:
        print(f"predicted {r['predicted_s']:.3f} s (simulated {r['makespan_s']:.3f} s + fixed {r['fixed_s']:.3f} s) "
              f"on {r['nodes']} nodes; recorded {r['measured_s']:.3f} s on {r['recorded_workers']} workers; "
              f"{r['rays_sent']} rays in {r['messages']} messages, {r['bytes_sent']} bytes; "
              f"{r['cache_messages']} cache-link messages, {r['cache_bytes']} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
