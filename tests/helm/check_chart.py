#!/usr/bin/env python3
"""The helm/dray chart, checked with the real tools (run by tests/helm/check.sh).

For the default values and for non-default ones (tests/helm/values-large.yaml, an
image-baked scene root, and the README's `helm install ... --set` values), the chart is
  1. linted strictly by Helm's own engine (helm-python-sdk: Helm v4's Go SDK; warnings
     fail, infos are printed),
  2. rendered by that engine, and every rendered manifest validated with
     `kubernetes-validate --strict -k KUBE_VERSION` (Kubernetes' OpenAPI schemas; unknown
     fields fail),
  3. checked for what a schema cannot see: labels, selectors that select the pods,
     the headless Service the StatefulSet names, worker addresses, probes on real ports,
     volumes at the same path in every pod, auth.existingSecret as token files (the API
     token for the coordinator only) and otlp.endpoint as OTEL_EXPORTER_OTLP_ENDPOINT, and
     every `dray` flag and variable the pods are given present in that subcommand's
     --help (when a dray binary is at hand),
and values that the schema or the templates must refuse are refused with their name.
Exits non-zero on any failure.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

import helm_python as helm

ROOT = Path(__file__).resolve().parents[2]
CHART = ROOT / "helm" / "dray"
HERE = Path(__file__).resolve().parent

failures: list[str] = []


def check(ok: bool, what: str) -> None:
    if not ok:
        failures.append(what)
        print(f"  FAIL: {what}")


def lint(label: str, values: dict, kube: str) -> None:
    report = helm.lint(str(CHART), values, strict=True, kube_version=f"v{kube}")
    for m in report.get("messages", []):
        sev = {0: "UNKNOWN", 1: "INFO", 2: "WARNING", 3: "ERROR"}.get(m["severity"], "?")
        print(f"  lint {sev}: {m['path']}: {m['error']}")
        check(m["severity"] < 2, f"{label}: lint {sev}: {m['path']}: {m['error']}")
    for e in report.get("errors", []):
        check(False, f"{label}: lint error: {e}")
    print(f"  lint --strict (kube v{kube}): {report.get('total_charts_linted')} chart linted")


def render(values: dict, name: str, namespace: str) -> dict[str, str]:
    with helm.Chart.load(str(CHART)) as chart:
        return chart.render(values, name=name, namespace=namespace, is_install=True)


def objects(manifests: dict[str, str]) -> list[dict]:
    out = []
    for path, text in sorted(manifests.items()):
        if path.endswith("NOTES.txt"):
            continue
        for doc in yaml.safe_load_all(text):
            if doc:
                doc["__template"] = path
                out.append(doc)
    return out


def validate(label: str, manifests: dict[str, str], out_dir: Path, kube: str, kv: str) -> None:
    if out_dir.exists():
        shutil.rmtree(out_dir)
    out_dir.mkdir(parents=True)
    files = []
    for path, text in sorted(manifests.items()):
        if path.endswith("NOTES.txt"):
            continue
        if not any(d for d in yaml.safe_load_all(text)):
            continue  # a template that rendered nothing for these values
        f = out_dir / path.replace("/", "__")
        f.write_text(text)
        files.append(str(f))
    cmd = [kv, "--strict", "-k", kube, *files]
    print(f"  $ kubernetes-validate --strict -k {kube} <{len(files)} manifests in {out_dir}>")
    r = subprocess.run(cmd, capture_output=True, text=True)
    for line in (r.stdout + r.stderr).splitlines():
        print(f"    {line}")
    check(r.returncode == 0, f"{label}: kubernetes-validate exited {r.returncode}")
    check(len(files) >= 4, f"{label}: only {len(files)} manifests rendered")


def dray_help(dray: str | None, sub: str) -> str | None:
    if not dray:
        return None
    r = subprocess.run([dray, sub, "--help"], capture_output=True, text=True)
    return r.stdout if r.returncode == 0 else None


def by_kind(objs: list[dict], kind: str) -> list[dict]:
    return [o for o in objs if o["kind"] == kind]


def semantics(label: str, objs: list[dict], v: dict, notes: str, namespace: str,
              dray: str | None) -> None:
    required_labels = [
        "app.kubernetes.io/name",
        "app.kubernetes.io/instance",
        "app.kubernetes.io/version",
        "app.kubernetes.io/managed-by",
        "helm.sh/chart",
    ]
    for o in objs:
        labels = o["metadata"].get("labels", {})
        for key in required_labels:
            check(key in labels, f"{label}: {o['kind']} {o['metadata']['name']} lacks label {key}")

    deps = by_kind(objs, "Deployment")
    sts = by_kind(objs, "StatefulSet")
    svcs = {s["metadata"]["name"]: s for s in by_kind(objs, "Service")}
    check(len(deps) == 1, f"{label}: {len(deps)} Deployments (want the coordinator)")
    check(len(sts) == 1, f"{label}: {len(sts)} StatefulSets (want the workers)")
    if len(deps) != 1 or len(sts) != 1:
        return
    coord, workers = deps[0], sts[0]

    def pod_labels(w: dict) -> dict:
        return w["spec"]["template"]["metadata"]["labels"]

    def selects(selector: dict, labels: dict) -> bool:
        return bool(selector) and all(labels.get(k) == x for k, x in selector.items())

    for w in (coord, workers):
        check(selects(w["spec"]["selector"]["matchLabels"], pod_labels(w)),
              f"{label}: {w['kind']} selector does not select its own pods")
    check(not selects(coord["spec"]["selector"]["matchLabels"], pod_labels(workers)),
          f"{label}: the coordinator's selector also selects worker pods")

    cc = coord["spec"]["template"]["spec"]["containers"][0]
    wc = workers["spec"]["template"]["spec"]["containers"][0]
    image = f"{v['image']['repository']}:{v['image']['tag'] or '0.1.0'}"
    for c in (cc, wc):
        check(c["image"] == image, f"{label}: image {c['image']} (want {image})")
        check(c["imagePullPolicy"] == v["image"]["pullPolicy"], f"{label}: pull policy")

    # The coordinator's Service: the public port, selecting the coordinator pod only.
    cport = v["coordinator"]["port"]
    csvc = svcs.get(coord["metadata"]["name"])
    check(csvc is not None, f"{label}: no Service named like the coordinator")
    if csvc:
        check(selects(csvc["spec"]["selector"], pod_labels(coord))
              and not selects(csvc["spec"]["selector"], pod_labels(workers)),
              f"{label}: the coordinator Service does not select exactly the coordinator")
        dash = v["coordinator"]["dashboard"]
        want_ports = [cport] + ([dash["port"]] if dash["enabled"] else [])
        check([p["port"] for p in csvc["spec"]["ports"]] == want_ports,
              f"{label}: coordinator Service ports {csvc['spec']['ports']} (want {want_ports})")
        check(csvc["spec"]["type"] == v["coordinator"]["service"]["type"], f"{label}: type")

    # The headless Service the StatefulSet names, publishing not-ready pods.
    hsvc = svcs.get(workers["spec"]["serviceName"])
    check(hsvc is not None, f"{label}: StatefulSet serviceName names no Service")
    if hsvc:
        check(hsvc["spec"].get("clusterIP") == "None", f"{label}: worker Service not headless")
        check(hsvc["spec"].get("publishNotReadyAddresses") is True,
              f"{label}: worker Service does not publish not-ready addresses")
        check(selects(hsvc["spec"]["selector"], pod_labels(workers)),
              f"{label}: the headless Service does not select the workers")
    check(workers["spec"]["replicas"] == v["workers"]["replicas"], f"{label}: replicas")

    # Ports, named ports and gRPC probes on ports the containers listen on.
    for c, port_value in ((cc, cport), (wc, v["workers"]["port"])):
        ports = {p["containerPort"] for p in c.get("ports", [])}
        check(port_value in ports, f"{label}: {c['name']} does not expose {port_value}")
        for probe in ("livenessProbe", "readinessProbe"):
            p = c.get(probe, {})
            check(p.get("grpc", {}).get("port") == port_value,
                  f"{label}: {c['name']} {probe} is not a gRPC probe on {port_value}: {p}")
    for s in (csvc, hsvc):
        if not s:
            continue
        target = coord if s is csvc else workers
        names = {p.get("name") for p in target["spec"]["template"]["spec"]["containers"][0]["ports"]}
        for p in s["spec"]["ports"]:
            check(p["targetPort"] in names,
                  f"{label}: Service {s['metadata']['name']} targets port {p['targetPort']} no container names")

    # The arguments: flags dray has, and addresses that reach each other.
    def flags(args: list[str]) -> dict[str, str]:
        out = {}
        for a in args[1:]:
            k, _, val = a.partition("=")
            out[k] = val
        return out

    ca, wa = cc["args"], wc["args"]
    check(ca[0] == "coordinator", f"{label}: coordinator args {ca}")
    check(wa[0] == "worker", f"{label}: worker args {wa}")
    cf, wf = flags(ca), flags(wa)
    check(cf.get("--listen") == f"0.0.0.0:{cport}", f"{label}: coordinator --listen {cf}")
    want_coord = f"http://{coord['metadata']['name']}.{namespace}.svc:{cport}"
    check(csvc is not None and csvc["metadata"]["name"] == coord["metadata"]["name"],
          f"{label}: the workers dial a Service name that is not the coordinator's")
    check(wf.get("--coordinator") == want_coord,
          f"{label}: worker --coordinator {wf.get('--coordinator')} (want {want_coord})")
    wport = v["workers"]["port"]
    check(wf.get("--listen") == f"0.0.0.0:{wport}", f"{label}: worker --listen {wf}")
    want_adv = (f"http://$(POD_NAME).{workers['spec']['serviceName']}.$(POD_NAMESPACE)"
                f".svc:{wport}")
    check(wf.get("--advertise") == want_adv,
          f"{label}: worker --advertise {wf.get('--advertise')} (want {want_adv})")
    env = {e["name"]: e.get("valueFrom", {}).get("fieldRef", {}).get("fieldPath")
           for e in wc.get("env", [])}
    check(env.get("POD_NAME") == "metadata.name" and env.get("POD_NAMESPACE") == "metadata.namespace",
          f"{label}: POD_NAME/POD_NAMESPACE env for $(VAR) expansion: {env}")
    check(wf.get("--memory-budget") == v["workers"]["memoryBudget"], f"{label}: --memory-budget")
    check(wf.get("--threads") == str(v["workers"]["threads"]), f"{label}: --threads")
    if v["workers"]["cacheHost"]:
        check(wf.get("--cache-listen") == f"0.0.0.0:{v['workers']['cachePort']}",
              f"{label}: --cache-listen {wf}")
    else:
        check("--no-cache-host" in wf and "--cache-listen" not in wf, f"{label}: cache host off")
    for extra in v["workers"]["extraArgs"]:
        check(extra in wa, f"{label}: worker extraArgs {extra} missing")

    for sub, given in (("coordinator", cf), ("worker", wf)):
        help_text = dray_help(dray, sub)
        if help_text is None:
            continue
        for flag in given:
            check(re.search(rf"(^|\s){re.escape(flag)}[\s=,]", help_text) is not None,
                  f"{label}: `dray {sub}` has no flag {flag}")

    # Volumes: the coordinator's --work-dir / --scene-root point at its mounts. With
    # workDir.mode "shared" the workers mount the work directory and the scenes at the
    # same paths and read packages there; with "fetch" they mount neither and fetch
    # packages from the coordinator into a cache of their own.
    def mounts(c: dict) -> dict[str, str]:
        return {m["name"]: m["mountPath"] for m in c.get("volumeMounts", [])}

    cm, wm = mounts(cc), mounts(wc)
    shared = v["workDir"]["mode"] == "shared"
    check(cm.get("work") == v["workDir"]["path"] == cf.get("--work-dir"),
          f"{label}: coordinator work dir mount {cm.get('work')} / --work-dir {cf.get('--work-dir')}")
    check(cf.get("--scene-root") == v["scenes"]["path"], f"{label}: --scene-root")
    if v["scenes"]["source"] == "image":
        check("scenes" not in cm, f"{label}: image scenes are not mounted")
    else:
        check(cm.get("scenes") == v["scenes"]["path"], f"{label}: scenes mounted at {cm.get('scenes')}")
    if shared:
        check(wm.get("work") == cm.get("work") and wm.get("scenes") == cm.get("scenes"),
              f"{label}: shared work dir / scenes mounted at {wm} in workers, {cm} in the coordinator")
        check(wf.get("--fetch-packages") == "never" and "package-cache" not in wm,
              f"{label}: shared mode worker flags {wf}")
    else:
        check("work" not in wm and "scenes" not in wm,
              f"{label}: workers that fetch packages mount {wm}")
        check(wf.get("--fetch-packages") == "auto" and wm.get("package-cache") is not None
              and wm.get("package-cache") == wf.get("--package-cache"),
              f"{label}: package cache mount {wm.get('package-cache')} / flags {wf}")
    claims = {}
    for w in (coord, workers):
        for vol in w["spec"]["template"]["spec"]["volumes"]:
            if "persistentVolumeClaim" in vol:
                claims.setdefault(vol["name"], set()).add(vol["persistentVolumeClaim"]["claimName"])
    created = f"{coord['metadata']['name'].removesuffix('-coordinator')}-work"
    want_work = v["workDir"]["existingClaim"] or (created if v["workDir"]["create"] else None)
    check(claims.get("work") == ({want_work} if want_work else None),
          f"{label}: work claim {claims.get('work')} (want {want_work or 'an emptyDir'})")
    # The job store: --state-dir on the coordinator's own volume (a claim unless told
    # otherwise), never mounted by workers; one coordinator at a time (Recreate).
    sd = v["stateDir"]
    state_claim = f"{coord['metadata']['name'].removesuffix('-coordinator')}-state"
    want_state = sd["existingClaim"] or (state_claim if sd["create"] else None)
    check(cm.get("state") == sd["path"] == cf.get("--state-dir") and "state" not in wm,
          f"{label}: state dir mount {cm.get('state')} / --state-dir {cf.get('--state-dir')}")
    check(claims.get("state") == ({want_state} if want_state else None),
          f"{label}: state claim {claims.get('state')} (want {want_state or 'an emptyDir'})")
    check(coord["spec"].get("strategy", {}).get("type") == "Recreate",
          f"{label}: the coordinator Deployment must use the Recreate strategy")
    check("job store" in notes, f"{label}: NOTES.txt does not say where jobs are kept")
    pvcs = sorted(p["metadata"]["name"] for p in by_kind(objs, "PersistentVolumeClaim"))
    want_pvcs = [created] if v["workDir"]["create"] and not v["workDir"]["existingClaim"] else []
    if sd["create"] and not sd["existingClaim"]:
        want_pvcs.append(state_claim)
    want_pvcs.sort()
    check(pvcs == want_pvcs, f"{label}: PVCs {pvcs} (want {want_pvcs})")
    if v["scenes"]["source"] == "pvc":
        check(claims.get("scenes") == {v["scenes"]["pvc"]["claimName"]}, f"{label}: scene claim")

    # Pods run as the image's non-root user.
    for w in (coord, workers):
        sc = w["spec"]["template"]["spec"].get("securityContext", {})
        check(sc.get("runAsNonRoot") is True, f"{label}: {w['kind']} may run as root")

    # NOTES.txt: how to reach the API and submit a job.
    port_forward = (f"kubectl --namespace {namespace} port-forward "
                    f"service/{coord['metadata']['name']} {cport}:{cport}")
    for want in (port_forward, "dray.v1.RenderService/SubmitJob",
                 "dray.v1.RenderService/WatchJob", "dray.v1.RenderService/GetImage",
                 "grpc.health.v1.Health/Check"):
        check(want in notes, f"{label}: NOTES.txt lacks {want!r}")
    dashboard(label, cc, cf, v, notes, namespace, coord["metadata"]["name"])
    mode = v.get("workDir", {}).get("mode", "fetch")
    check(f"(workDir.mode {mode}" in notes,
          f"{label}: NOTES.txt does not say how workers get packages (workDir.mode {mode})")
    auth_and_otlp(label, coord, workers, v, notes, dray)


def dashboard(label: str, cc: dict, cf: dict, v: dict, notes: str, namespace: str,
              coord_name: str) -> None:
    """coordinator.dashboard: off, no trace of it; on, --http-listen on its port, a
    container port named http (the Service's targetPort) and a port-forward in NOTES."""
    dash = v["coordinator"]["dashboard"]
    ports = {p["name"]: p["containerPort"] for p in cc.get("ports", [])}
    forward = (f"kubectl --namespace {namespace} port-forward service/{coord_name} "
               f"{dash['port']}:{dash['port']}")
    if dash["enabled"]:
        check(cf.get("--http-listen") == f"0.0.0.0:{dash['port']}",
              f"{label}: coordinator --http-listen {cf.get('--http-listen')}")
        check(ports.get("http") == dash["port"], f"{label}: container ports {ports}")
        check(forward in notes, f"{label}: NOTES.txt lacks {forward!r}")
    else:
        check("--http-listen" not in cf and "http" not in ports and "dashboard" not in notes,
              f"{label}: the dashboard is off but appears: {cf} {ports}")


def container_env(c: dict) -> dict[str, str | None]:
    return {e["name"]: e.get("value") for e in c.get("env", [])}


def auth_and_otlp(label: str, coord: dict, workers: dict, v: dict, notes: str,
                  dray: str | None) -> None:
    """auth.existingSecret reaches the pods as token files (DRAY_AUTH_TOKEN_FILE for the
    coordinator only, DRAY_CLUSTER_TOKEN_FILE for both) in the Secret mounted read-only,
    and otlp.endpoint as OTEL_EXPORTER_OTLP_ENDPOINT; dray reads both variables."""
    secret = v["auth"]["existingSecret"]
    endpoint = v["otlp"]["endpoint"]
    for w, component in ((coord, "coordinator"), (workers, "worker")):
        pod = w["spec"]["template"]["spec"]
        c = pod["containers"][0]
        env = container_env(c)
        vols = {vol["name"]: vol for vol in pod.get("volumes", [])}
        mounts = {m["name"]: m for m in c.get("volumeMounts", [])}
        want_files = {"DRAY_CLUSTER_TOKEN_FILE": v["auth"]["clusterTokenKey"]}
        if component == "coordinator":
            want_files["DRAY_AUTH_TOKEN_FILE"] = v["auth"]["apiTokenKey"]
        if not secret:
            check(not any(k in env for k in ("DRAY_AUTH_TOKEN_FILE", "DRAY_CLUSTER_TOKEN_FILE"))
                  and "auth" not in vols and "auth" not in mounts,
                  f"{label}: {component} has token files without auth.existingSecret")
        else:
            vol, mount = vols.get("auth"), mounts.get("auth")
            check(vol is not None and vol.get("secret", {}).get("secretName") == secret,
                  f"{label}: {component} does not mount Secret {secret}: {vol}")
            check(mount is not None and mount.get("readOnly") is True,
                  f"{label}: {component} auth mount is not read-only: {mount}")
            if vol and mount:
                items = {i["path"]: i["key"] for i in vol["secret"].get("items", [])}
                for var, key in want_files.items():
                    path = env.get(var) or ""
                    check(path.startswith(mount["mountPath"] + "/"),
                          f"{label}: {component} {var}={path} is not in the auth mount")
                    name = path.removeprefix(mount["mountPath"] + "/")
                    check(items.get(name) == key,
                          f"{label}: {component} {var} is file {name}, Secret items {items} (want key {key})")
                check(len(items) == len(want_files),
                      f"{label}: {component} gets Secret keys {sorted(items.values())}")
            if component == "worker":
                check("DRAY_AUTH_TOKEN_FILE" not in env, f"{label}: workers get the API token")
        check(env.get("OTEL_EXPORTER_OTLP_ENDPOINT") == (endpoint or None),
              f"{label}: {component} OTEL_EXPORTER_OTLP_ENDPOINT={env.get('OTEL_EXPORTER_OTLP_ENDPOINT')}"
              f" (want {endpoint or 'unset'})")
        # Every variable dray is given is one its --help names.
        help_text = dray_help(dray, component)
        if help_text is not None:
            for var in env:
                if var.startswith(("DRAY_", "OTEL_EXPORTER_")):
                    check(f"[env: {var}=" in help_text,
                          f"{label}: `dray {component} --help` names no variable {var}")
    if secret:
        check('-H "authorization: Bearer $token"' in notes and "--auth-token-file api.token" in notes
              and f"get secret {secret}" in notes,
              f"{label}: NOTES.txt does not show how to present the API token")
    else:
        check("no auth.existingSecret" in notes, f"{label}: NOTES.txt does not say the API is open")
    if endpoint:
        check(f"exported to {endpoint}" in notes, f"{label}: NOTES.txt does not name {endpoint}")


def refused(label: str, values: dict, must_mention: str) -> None:
    try:
        render(values, "dray", "dray")
    except helm.HelmError as e:
        msg = str(e)
        ok = must_mention in msg
        print(f"  refused ({label}): {msg.strip().splitlines()[-1][:160]}")
        check(ok, f"refusal of {label} does not mention {must_mention!r}: {msg}")
        return
    check(False, f"{label}: the chart rendered values it must refuse")


def deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, x in over.items():
        out[k] = deep_merge(out[k], x) if isinstance(x, dict) and isinstance(out.get(k), dict) else x
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--kube-version", default="1.30.0")
    ap.add_argument("--out", default=str(ROOT / "target" / "helm-rendered"))
    ap.add_argument("--kubernetes-validate", default=shutil.which("kubernetes-validate")
                    or str(Path(sys.executable).parent / "kubernetes-validate"))
    ap.add_argument("--dray", default=os.environ.get("DRAY_BIN")
                    or str(ROOT / "target" / "release" / "dray"))
    a = ap.parse_args()
    kube = a.kube_version
    dray = a.dray if Path(a.dray).is_file() else None
    print(f"helm engine {helm.helm_sdk_version()} (helm-python-sdk {helm.__version__}); chart {CHART}")
    if dray is None:
        print(f"  NOTE: no dray binary at {a.dray}: the pods' flags are not checked against "
              "`dray coordinator|worker --help` (build it, or set DRAY_BIN)")

    with helm.Chart.load(str(CHART)) as chart:
        defaults = chart.values
        meta = chart.metadata
    check(meta.get("apiVersion") == "v2", "Chart.yaml apiVersion is not v2")

    large = helm.values_from_yaml((HERE / "values-large.yaml").read_text())
    cases = [
        ("default values", {}, "dray", "dray"),
        ("values-large.yaml (8 workers, PVC scenes, resources)", large, "farm", "render"),
        ("image-baked scenes, 1 worker, existing work claim shared with the workers",
         {"scenes": {"source": "image", "path": "/opt/scenes"}, "workers": {"replicas": 1},
          "workDir": {"existingClaim": "shared-work", "mode": "shared"}}, "dray", "prod"),
        ("packages fetched, a work claim the chart creates, a bounded package cache",
         {"workDir": {"create": True, "size": "5Gi"},
          "workers": {"packageCacheSizeLimit": "10Gi"}}, "dray", "dray"),
        ("the job store on an existing claim",
         {"stateDir": {"existingClaim": "dray-jobs"}}, "dray", "dray"),
        ("the job store on an emptyDir",
         {"stateDir": {"create": False}}, "dray", "dray"),
    ]
    # The README's `helm install render helm/dray --namespace render --set ...`, parsed as
    # Helm parses --set (so "6Gi" must stay a string).
    readme = helm.parse_set_string(
        "image.repository=registry.example.com/dray,image.tag=0.1.0,workers.replicas=4,"
        "workers.memoryBudget=6Gi,workers.resources.limits.memory=8Gi")
    cases.append(("the README's helm install --set values", readme, "render", "render"))
    cases.append(("auth from a Secret with its own keys, OTLP export",
                  {"auth": {"existingSecret": "render-tokens", "apiTokenKey": "api.tok",
                            "clusterTokenKey": "members"},
                   "otlp": {"endpoint": "http://otel-collector.observability.svc:4317"}},
                  "dray", "dray"))
    cases.append(("the web dashboard on its own port, with auth",
                  {"coordinator": {"dashboard": {"enabled": True, "port": 8088}},
                   "auth": {"existingSecret": "dray-auth"}}, "dray", "dray"))
    for i, (label, values, name, ns) in enumerate(cases):
        print(f"== {label} (release {name}, namespace {ns})")
        lint(label, values, kube)
        try:
            manifests = render(values, name, ns)
        except helm.HelmError as e:
            check(False, f"{label}: render failed: {e}")
            continue
        kinds = sorted(f"{o['kind']}/{o['metadata']['name']}" for o in objects(manifests))
        print(f"  rendered: {', '.join(kinds)}")
        validate(label, manifests, Path(a.out) / f"case{i}", kube, a.kubernetes_validate)
        notes = next((t for p, t in manifests.items() if p.endswith("NOTES.txt")), "")
        semantics(label, objects(manifests), deep_merge(defaults, values), notes, ns, dray)
        if name == "render" and values is readme:
            names = {f"{o['kind']}/{o['metadata']['name']}" for o in objects(manifests)}
            for want in ("Service/render-dray-coordinator", "StatefulSet/render-dray-workers"):
                check(want in names, f"{label}: no {want} (the README names it)")

    print("== values the chart must refuse")
    refused("workers.replicas=-1", {"workers": {"replicas": -1}}, "replicas")
    refused("workers.memoryBudget=1.5G", {"workers": {"memoryBudget": "1.5G"}}, "memoryBudget")
    refused("workers.memoryBudget as a number", {"workers": {"memoryBudget": 1073741824}},
            "memoryBudget")
    refused("a misspelt key workers.replica", {"workers": {"replica": 3}}, "replica")
    refused("scenes.source=pvc without a claim", {"scenes": {"source": "pvc"}}, "claimName")
    refused("scenes.source=nfs", {"scenes": {"source": "nfs"}}, "source")
    refused("image.pullPolicy=Sometimes", {"image": {"pullPolicy": "Sometimes"}}, "pullPolicy")
    refused("a shared work dir without a claim", {"workDir": {"mode": "shared"}}, "workDir")
    refused("workDir.mode=nfs", {"workDir": {"mode": "nfs"}}, "mode")
    refused("otlp.endpoint without a scheme", {"otlp": {"endpoint": "collector:4317"}}, "endpoint")
    refused("auth.existingSecret not a Secret name", {"auth": {"existingSecret": "My_Secret"}},
            "existingSecret")
    refused("auth.apiTokenKey empty", {"auth": {"existingSecret": "s", "apiTokenKey": ""}},
            "apiTokenKey")

    refused("coordinator.dashboard.port equal to coordinator.port",
            {"coordinator": {"dashboard": {"enabled": True, "port": 50051}}}, "dashboard.port")
    refused("coordinator.dashboard.port=0",
            {"coordinator": {"dashboard": {"enabled": True, "port": 0}}}, "port")

    if failures:
        print(f"\nchart test FAILED: {len(failures)} problem(s):")
        for f in failures:
            print(f"  - {f}")
        return 1
    print(f"\nchart test passed: {len(cases)} value sets linted (strict), rendered and "
          f"validated (kubernetes-validate --strict -k {kube}); 14 bad value sets refused")
    return 0


if __name__ == "__main__":
    sys.exit(main())
