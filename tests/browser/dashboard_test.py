#!/usr/bin/env python3
"""The web dashboard in a real browser (run by tests/browser/run.sh).

Headless Chromium, driven over WebDriver by Selenium, against a real
`dray cluster --workers 2 --http-listen 127.0.0.1:PORT`:
  1. the page loads and its live updates connect;
  2. a job submitted from the page's form appears in the jobs table;
  3. its image is shown, and the last frame has the pixels of `dray render`'s PNG for
     the same spec (decoded and compared); frames shown while it runs (when the
     coordinator serves progressive images) change as samples are added;
  4. cancelling a running job from the page asks first (a second click on the armed
     button), then cancels it (checked through gRPC with grpcurl: GetJob says
     CANCELLED); the cancelled job retried from the page is a new job linked to it
     (GetJob's retriedFrom), and the finished job's PNG and EXR download as attachments
     (the PNG the bytes the page shows, the EXR GetImage's);
  5. the workers are listed with their domains, under their names (worker-1, worker-2);
     a frame range submitted from the form is a job group: its frames are listed, each
     marked with its frame and group (ListJobs of the group agrees), and a frame's PNG
     downloads (GetImage's bytes);
  6. 100 jobs are listed at once, and older ones are a page away;
  7. with --auth-token-file, the page shows its login, the API refuses requests without
     the token (401) and state-changing requests without the CSRF header (403), a wrong
     token is refused, and the right one opens the dashboard with an HttpOnly cookie.
No assertion is on time: each step waits for what it needs with a generous bound.
Screenshots go to --artifacts (dashboard.png is the README's).
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import json
import subprocess
import sys
import tempfile
import time
import traceback
import urllib.error
import urllib.request
from pathlib import Path

from PIL import Image
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
from selenium.webdriver.common.by import By

from cluster import Cluster, wait_for

# The job the page submits and `dray render` renders: the form's defaults for the rest
# (integrator path, max depth 5, seed 0; domains and schedule do not change the bits).
SCENE, WIDTH, HEIGHT, SPP = "cornell", 160, 120, 256
# A job that runs long enough to be cancelled while RUNNING.
LONG_SPP = 65536

passed: list[str] = []
skipped: list[str] = []
SKIPPED = "skipped"


def step(name: str):
    """A check; one that returns SKIPPED could not run against this coordinator."""
    def wrap(f):
        def run(*a, **kw):
            t = time.monotonic()
            if f(*a, **kw) == SKIPPED:
                skipped.append(name)
                print(f"skip - {name}", flush=True)
                return
            passed.append(name)
            print(f"ok - {name} ({time.monotonic() - t:.1f} s)", flush=True)
        return run
    return wrap


def browser(artifacts: Path) -> webdriver.Chrome:
    o = webdriver.ChromeOptions()
    o.binary_location = "/usr/bin/chromium"
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=1280,1000", "--hide-scrollbars"):
        o.add_argument(a)
    d = webdriver.Chrome(service=Service("/usr/bin/chromedriver",
                                         log_output=str(artifacts / "chromedriver.log")),
                         options=o)
    d.set_script_timeout(120)
    return d


def shown(d, element_id: str) -> bool:
    return d.find_element(By.ID, element_id).is_displayed()


def rows(d) -> list[dict]:
    return d.execute_script(
        "return [...document.querySelectorAll('#jobs tbody tr')]"
        ".map(r => ({id: r.dataset.id, state: r.dataset.state}))")


def fill_form(d, values: dict) -> None:
    form = d.find_element(By.ID, "submit-form")
    for name, value in values.items():
        el = form.find_element(By.NAME, name)
        if el.tag_name == "select":
            d.execute_script("arguments[0].value = arguments[1]", el, str(value))
        else:
            el.clear()
            el.send_keys(str(value))
    d.find_element(By.ID, "submit-button").click()


def displayed_png(d) -> bytes:
    """The bytes of the image the page shows (its blob, fetched inside the page)."""
    b64 = d.execute_async_script("""
        const done = arguments[arguments.length - 1];
        fetch(document.getElementById('preview').src)
          .then(r => r.arrayBuffer())
          .then(b => { const u = new Uint8Array(b); let s = '';
                       for (let i = 0; i < u.length; i += 0x8000)
                         s += String.fromCharCode.apply(null, u.subarray(i, i + 0x8000));
                       done(btoa(s)); })
          .catch(e => done('ERROR ' + e));""")
    if b64.startswith("ERROR"):
        raise AssertionError(f"cannot read the displayed image: {b64}")
    return base64.b64decode(b64)


def pixels(png: bytes) -> tuple[tuple[int, int], bytes]:
    im = Image.open(io.BytesIO(png)).convert("RGB")
    return im.size, im.tobytes()


def http(url: str, method: str = "GET", headers: dict | None = None,
         body: bytes | None = None) -> tuple[int, dict]:
    req = urllib.request.Request(url, method=method, headers=headers or {}, data=body)
    try:
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.status, json.loads(r.read() or b"{}")
    except urllib.error.HTTPError as e:
        return e.code, json.loads(e.read() or b"{}")


@step("the page loads and its live updates connect")
def page_loads(d, c: Cluster, artifacts: Path) -> None:
    d.get(c.url + "/")
    wait_for("the app to show", lambda: shown(d, "app"))
    wait_for("live updates", lambda: d.find_element(By.ID, "live").text == "live")
    assert d.title == "dray", d.title
    d.save_screenshot(str(artifacts / "loaded.png"))


@step("a job submitted from the page appears, and its image is dray render's")
def submit_and_image(d, c: Cluster, artifacts: Path, dray: str, tmp: Path) -> None:
    fill_form(d, {"scene": SCENE, "width": WIDTH, "height": HEIGHT, "spp": SPP,
                  "label": "browser test"})
    job = wait_for("the submitted job's row", lambda: d.execute_script(
        "const r = document.querySelector('#jobs tbody tr.selected'); return r && r.dataset.id"))
    assert any(r["id"] == job for r in rows(d)), rows(d)
    # Frames while it runs, when the coordinator has progressive images (each frame
    # carries its samples per pixel); then the last one.
    frames: dict[str, str] = {}

    def finished() -> bool:
        img = d.find_element(By.ID, "preview")
        samples = img.get_attribute("data-samples")
        version = img.get_attribute("data-version")
        if samples is not None and version != "0" and samples not in frames:
            frames[samples] = hashlib.sha256(displayed_png(d)).hexdigest()
        state = next((r["state"] for r in rows(d) if r["id"] == job), None)
        return state == "SUCCEEDED" and version != "0" and (
            samples is None or samples == str(SPP))

    wait_for(f"job {job} to succeed with its image shown", finished, every=0.1)
    d.save_screenshot(str(artifacts / "job-succeeded.png"))
    if frames:
        print(f"   frames seen at samples per pixel {sorted(frames, key=int)}")
        assert len(set(frames.values())) == len(frames), f"a new pass left the image as it was: {frames}"
        assert len(frames) >= 2, f"only one frame seen while the job ran: {frames}"
    else:
        print("   NOTE: this coordinator serves no progressive images (no x-dray-samples): "
              "only the finished image was checked")
    shown_png = displayed_png(d)
    ref = tmp / "render.png"
    subprocess.run([dray, "render", SCENE, "--width", str(WIDTH), "--height", str(HEIGHT),
                    "--spp", str(SPP), "--output", str(ref), "-q"], check=True, timeout=600)
    (size_a, a), (size_b, b) = pixels(shown_png), pixels(ref.read_bytes())
    assert size_a == size_b, f"the page shows {size_a}, dray render made {size_b}"
    differing = sum(1 for i in range(0, len(a), 3) if a[i:i + 3] != b[i:i + 3])
    assert differing == 0, f"{differing} pixels differ from dray render's PNG"


@step("cancelling a running job from the page cancels it (GetJob over gRPC)")
def cancel_from_page(d, c: Cluster, artifacts: Path) -> None:
    fill_form(d, {"scene": SCENE, "width": 320, "height": 240, "spp": LONG_SPP,
                  "domains": 4, "label": "to cancel"})
    # Found by its label: the row selected a moment ago may still be the previous job's
    # (a finished one, which would never run) until the page selects the new one.
    job = wait_for("the long job's row", lambda: d.execute_script(
        "const r = [...document.querySelectorAll('#jobs tbody tr')]"
        ".find(r => r.textContent.includes('to cancel'));"
        "return r && r.querySelector('td small') && r.dataset.id"))
    wait_for("the long job to run", lambda: any(
        r["id"] == job and r["state"] == "RUNNING" for r in rows(d)))
    if has_list_workers(c):
        # While it runs: its 4 domains with their owners, and domains at the workers.
        wait_for("its 4 domains in the ownership view", lambda: d.execute_script(
            "return document.querySelectorAll(`#ownership [data-job='${arguments[0]}'] .domain`)"
            ".length", job) == 4)
        wait_for("domains listed at the workers", lambda: d.execute_script(
            "return document.querySelectorAll('#workers tbody td.chips .chip').length") > 0)
        d.save_screenshot(str(artifacts / "running-domains.png"))
    cancel_twice(d, job)
    wait_for("the page to show it CANCELLED", lambda: any(
        r["id"] == job and r["state"] == "CANCELLED" for r in rows(d)))
    got = c.grpcurl(GRPCURL, "GetJob", {"jobId": job})
    state = got["job"]["progress"]["state"]
    assert state == "JOB_STATE_CANCELLED", got
    d.save_screenshot(str(artifacts / "cancelled.png"))
    retry_from_page(d, c, job, artifacts)


def cancel_twice(d, job: str) -> None:
    """Cancel `job` as a person does: the first click only arms the button (nothing is
    cancelled: checked), the second, on "really cancel?", cancels."""
    wait_for("the cancel button to take the click", lambda: click(
        d, f'button[data-cancel="{job}"]:not([data-armed])'))
    wait_for("the button to ask for confirmation", lambda: d.execute_script(
        "return !!document.querySelector(`button[data-cancel='${arguments[0]}'][data-armed]`)",
        job))
    assert any(r["id"] == job and r["state"] != "CANCELLED" for r in rows(d)), \
        "the first click alone cancelled the job"
    wait_for("the confirmation to take the click", lambda: click(
        d, f'button[data-cancel="{job}"][data-armed]'))


def retry_from_page(d, c: Cluster, job: str, artifacts: Path) -> None:
    """Retry the cancelled `job` with the page's button: a new job, linked to it."""
    wait_for("a click on the cancelled job", lambda: click(d, f'#jobs tbody tr[data-id="{job}"]'))
    wait_for("the retry button", lambda: click(d, '#job-operator button[data-op="retry"]'))
    new = wait_for("the retried job selected", lambda: (lambda s: s if s and s != job else None)(
        d.execute_script("return document.querySelector('#jobs tbody tr.selected')?.dataset.id")))
    got = c.grpcurl(GRPCURL, "GetJob", {"jobId": new})
    assert got["job"].get("retriedFrom") == job, got
    wait_for("the page to show where it was retried from", lambda: d.execute_script(
        "return document.querySelector(`#job-operator a[data-job='${arguments[0]}']`) != null",
        job))
    events = c.grpcurl(GRPCURL, "GetJob", {"jobId": job})["job"].get("events", [])
    assert any(e.get("kind") == "JOB_EVENT_KIND_RETRIED" and new in e.get("message", "")
               for e in events), events
    d.save_screenshot(str(artifacts / "retried.png"))
    wait_for(f"the retried job {new} in the table", lambda: any(r["id"] == new for r in rows(d)))
    if c.grpcurl(GRPCURL, "GetJob", {"jobId": new})["job"]["progress"]["state"] not in (
            "JOB_STATE_SUCCEEDED", "JOB_STATE_FAILED", "JOB_STATE_CANCELLED"):
        cancel_twice(d, new)
        wait_for("the retried job CANCELLED", lambda: any(
            r["id"] == new and r["state"] == "CANCELLED" for r in rows(d)))


def fetch_in_page(d, url: str) -> tuple[int, str, bytes]:
    """GET `url` from inside the page (its cookie and origin): status, the
    Content-Disposition header and the body."""
    got = d.execute_async_script("""
        const done = arguments[arguments.length - 1];
        fetch(arguments[0], {credentials: 'same-origin'})
          .then(async r => { const u = new Uint8Array(await r.arrayBuffer()); let s = '';
                             for (let i = 0; i < u.length; i += 0x8000)
                               s += String.fromCharCode.apply(null, u.subarray(i, i + 0x8000));
                             done([r.status, r.headers.get('content-disposition') || '', btoa(s)]); })
          .catch(e => done([0, 'ERROR ' + e, '']));""", url)
    return got[0], got[1], base64.b64decode(got[2])


@step("the finished job's PNG and EXR download from the page")
def download_from_page(d, c: Cluster, artifacts: Path) -> None:
    job = d.execute_script(
        "return [...document.querySelectorAll('#jobs tbody tr')]"
        ".find(r => r.dataset.state === 'SUCCEEDED').dataset.id")
    wait_for("a click on the finished job", lambda: click(d, f'#jobs tbody tr[data-id="{job}"]'))
    wait_for("its image", lambda: d.find_element(By.ID, "preview").get_attribute("data-version") != "0")
    links = wait_for("the download links", lambda: d.execute_script(
        "const a = [...document.querySelectorAll('#job-operator a.download')].map(a => a.href);"
        "return a.length === 2 ? a : null"))
    png = [u for u in links if u.endswith("image.png")][0]
    exr = [u for u in links if u.endswith("image.exr")][0]
    status, disposition, body = fetch_in_page(d, png)
    assert status == 200, (status, disposition)
    assert disposition == f'attachment; filename="{job}.png"', disposition
    assert body == displayed_png(d), "the downloaded PNG is not the image the page shows"
    status, disposition, body = fetch_in_page(d, exr)
    assert status == 200 and disposition == f'attachment; filename="{job}.exr"', disposition
    # (160x120: well within grpcurl's 4 MiB default message limit.)
    got = c.grpcurl(GRPCURL, "GetImage", {"jobId": job, "format": "IMAGE_FORMAT_EXR"})
    assert body == base64.b64decode(got["data"]), "the downloaded EXR is not GetImage's"


# A small frame range: frames 1 to 3 of a tiny cornell at 24 fps (a procedural scene
# has no animation: each frame is the rest pose, an ordinary job of its own).
FRAMES, FRAME_COUNT = "1..3", 3


@step("a frame range from the page is a job group: frames listed, one downloaded")
def frames_from_page(d, c: Cluster, artifacts: Path) -> None:
    fill_form(d, {"scene": SCENE, "width": 32, "height": 24, "spp": 4,
                  "label": "frame range", "frames": FRAMES, "fps": 24})
    # The form keeps what it was given: the submissions after this one are lone jobs.
    form = d.find_element(By.ID, "submit-form")
    for name in ("frames", "fps"):
        form.find_element(By.NAME, name).clear()

    def listed():
        got = d.execute_script(
            "return [...document.querySelectorAll('#jobs tbody tr')]"
            ".filter(r => r.textContent.includes('frame range') && r.querySelector('small.group'))"
            ".map(r => ({id: r.dataset.id, state: r.dataset.state,"
            "            marked: r.querySelector('small.group').textContent}))")
        done = len(got) == FRAME_COUNT and all(r["state"] == "SUCCEEDED" for r in got)
        return got if done else None

    frames = wait_for(f"the group's {FRAME_COUNT} frames listed, SUCCEEDED", listed)
    marks = sorted(r["marked"] for r in frames)
    groups = {m.split(" of ", 1)[1] for m in marks}
    assert len(groups) == 1, f"the frames are marked with several groups: {marks}"
    group = groups.pop()
    assert [m.split(" of ", 1)[0] for m in marks] == ["frame 1", "frame 2", "frame 3"], marks
    got = c.grpcurl(GRPCURL, "ListJobs", {"groupId": group})
    api = sorted(j["jobId"] for j in got.get("jobs", []))
    assert api == sorted(r["id"] for r in frames), f"the page lists {frames}, ListJobs {api}"
    d.save_screenshot(str(artifacts / "frames.png"))
    # Frame 2's PNG, from its download link.
    second = next(r["id"] for r in frames if r["marked"].startswith("frame 2 "))
    wait_for("a click on frame 2", lambda: click(d, f'#jobs tbody tr[data-id="{second}"]'))
    link = wait_for("frame 2's PNG link", lambda: d.execute_script(
        "const a = [...document.querySelectorAll('#job-operator a.download')]"
        ".map(a => a.href).filter(h => h.includes(arguments[0]) && h.endsWith('image.png'));"
        "return a.length === 1 ? a[0] : null", second))
    status, disposition, body = fetch_in_page(d, link)
    assert status == 200, (status, disposition)
    assert disposition == f'attachment; filename="{second}.png"', disposition
    want = c.grpcurl(GRPCURL, "GetImage", {"jobId": second, "format": "IMAGE_FORMAT_PNG"})
    assert body == base64.b64decode(want["data"]), "the downloaded frame is not GetImage's PNG"
    assert pixels(body)[0] == (32, 24), pixels(body)[0]


def click(d, css: str) -> bool:
    """Click the element `css` selects; False (try again) when a live update redrew it
    between finding and clicking."""
    try:
        d.find_element(By.CSS_SELECTOR, css).click()
        return True
    except (StaleElementReferenceException, NoSuchElementException):
        return False


def has_list_workers(c: Cluster) -> bool:
    r = subprocess.run([GRPCURL, "-plaintext", c.grpc, "describe", "dray.v1.RenderService"],
                       capture_output=True, text=True, timeout=120)
    return "ListWorkers" in r.stdout


@step("the workers are listed with their domains")
def workers_listed(d, c: Cluster, artifacts: Path) -> None:
    if not has_list_workers(c):
        print("   NOTE: this coordinator has no ListWorkers rpc yet: the workers panel was "
              "NOT checked")
        return SKIPPED
    wait_for("two workers in the table", lambda: d.execute_script(
        "return document.querySelectorAll('#workers tbody tr').length") == 2)
    ids = d.execute_script(
        "return [...document.querySelectorAll('#workers tbody tr')].map(r => r.dataset.worker)")
    got = c.grpcurl(GRPCURL, "ListWorkers", {})
    want = sorted(w.get("workerId", w.get("id", "")) for w in got.get("workers", []))
    assert sorted(ids) == want, f"the page lists {ids}, ListWorkers {want}"
    # Under the names dray cluster gave them, as ListWorkers and the logs say.
    names = d.execute_script(
        "return [...document.querySelectorAll('#workers tbody tr')].map(r => r.dataset.name)")
    listed = sorted(w.get("name", "") for w in got.get("workers", []))
    assert sorted(names) == listed == ["worker-1", "worker-2"], \
        f"the page names {names}, ListWorkers {listed}"
    shown = d.execute_script(
        "return [...document.querySelectorAll('#workers tbody .worker-name')].map(e => e.textContent)")
    assert sorted(shown) == listed, f"the page shows {shown}"


@step("100 jobs listed at once, older ones a page away")
def many_jobs(d, c: Cluster, artifacts: Path) -> None:
    # Tiny jobs through the dashboard's API (the same SubmitJob), one after another. On a
    # loaded machine they can arrive faster than they finish: beyond --max-jobs active
    # jobs the coordinator answers 429 (RESOURCE_EXHAUSTED), and a client waits for room,
    # as this one does (a 429 that never clears still fails, at the deadline).
    for i in range(101):
        body = json.dumps({"scene": "cornell", "width": 8, "height": 8, "spp": 1,
                           "label": f"many {i}"}).encode()
        deadline = time.monotonic() + 300
        while True:
            status, got = http(c.url + "/api/jobs", "POST",
                               {"Content-Type": "application/json", "X-Dray-Csrf": "1"}, body)
            if status != 429 or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert status == 200, (status, got)
    wait_for("100 rows and an older page", lambda: len(rows(d)) == 100 and d.execute_script(
        "return !!document.querySelector('#jobs-pager button')"))
    wait_for("a click on " + "#jobs-pager button", lambda: click(d, "#jobs-pager button"))
    wait_for("the older page", lambda: 0 < len(rows(d)) < 100)
    wait_for("a click on " + '#jobs-pager button[data-page="newest"]', lambda: click(d, '#jobs-pager button[data-page="newest"]'))
    wait_for("the newest page again", lambda: len(rows(d)) == 100)


def readme_screenshot(d, artifacts: Path) -> None:
    """dashboard.png: the finished job selected, workers listed (the README's picture)."""
    job = d.execute_script(
        "return [...document.querySelectorAll('#jobs tbody tr')]"
        ".find(r => r.dataset.state === 'SUCCEEDED').dataset.id")
    wait_for("a click on " + f'#jobs tbody tr[data-id="{job}"]', lambda: click(d, f'#jobs tbody tr[data-id="{job}"]'))
    wait_for("its image", lambda: d.find_element(By.ID, "preview").get_attribute("data-version") != "0")
    # The whole page, not just the window.
    height = d.execute_script("return document.documentElement.scrollHeight")
    d.set_window_size(1280, height + 140)
    d.save_screenshot(str(artifacts / "dashboard.png"))
    d.set_window_size(1280, 1000)


@step("with a token: login shown, API refused without it, CSRF refused, login works")
def token_required(d, c: Cluster, artifacts: Path) -> None:
    token = c.token_file.read_text().strip()
    d.delete_all_cookies()
    d.get(c.url + "/")
    wait_for("the login form", lambda: shown(d, "login"))
    assert not shown(d, "app")
    d.save_screenshot(str(artifacts / "login.png"))
    status, body = http(c.url + "/api/jobs")
    assert status == 401 and body.get("code") == "UNAUTHENTICATED", (status, body)
    status, _ = http(c.url + "/api/jobs", headers={"Authorization": f"Bearer {token}x"})
    assert status == 401, status
    status, body = http(c.url + "/api/jobs", headers={"Authorization": f"Bearer {token}"})
    assert status == 200 and "jobs" in body, (status, body)
    in_page = "return fetch('/api/jobs').then(r => r.status)"
    assert d.execute_script(in_page) == 401
    # A wrong token is refused on the page.
    d.find_element(By.ID, "token").send_keys("not-the-api-token-at-all")
    d.find_element(By.CSS_SELECTOR, "#login-form button").click()
    wait_for("the refusal", lambda: d.find_element(By.ID, "login-error").text != "")
    assert not shown(d, "app")
    # The right one opens the dashboard; its cookie is out of the page's reach.
    d.find_element(By.ID, "token").clear()
    d.find_element(By.ID, "token").send_keys(token)
    d.find_element(By.CSS_SELECTOR, "#login-form button").click()
    wait_for("the app after logging in", lambda: shown(d, "app"))
    wait_for("live updates", lambda: d.find_element(By.ID, "live").text == "live")
    assert "dray_session" not in d.execute_script("return document.cookie")
    assert d.execute_script(in_page) == 200
    # With the cookie, a state-changing request without the CSRF header is refused.
    csrf = d.execute_script("""
        return fetch('/api/jobs', {method: 'POST', headers: {'Content-Type': 'application/json'},
          body: JSON.stringify({scene: 'cornell', width: 8, height: 8, spp: 1})}).then(r => r.status)""")
    assert csrf == 403, csrf
    jobs = c.grpcurl(GRPCURL, "ListJobs", {})
    assert not jobs.get("jobs"), f"a refused request made a job: {jobs}"


GRPCURL = "grpcurl"


def main() -> int:
    global GRPCURL
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dray", required=True)
    ap.add_argument("--grpcurl", required=True)
    ap.add_argument("--artifacts", required=True)
    a = ap.parse_args()
    GRPCURL = a.grpcurl
    artifacts = Path(a.artifacts).resolve()
    artifacts.mkdir(parents=True, exist_ok=True)
    for old in [*artifacts.glob("*.png"), *artifacts.glob("*.log")]:
        old.unlink()
    dray = str(Path(a.dray).resolve())
    failed: list[str] = []
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="dray-browser-") as tmp_name:
        tmp = Path(tmp_name)
        d = browser(artifacts)
        clusters: list[Cluster] = []
        try:
            def guarded(name: str, f, *args) -> None:
                try:
                    f(*args)
                except Exception:  # noqa: BLE001 - every step reports, the run goes on
                    failed.append(name)
                    print(f"FAIL - {name}\n{traceback.format_exc()}", flush=True)
                    d.save_screenshot(str(artifacts / f"failed-{len(failed)}.png"))

            c = Cluster(dray, artifacts / "cluster.log")
            clusters.append(c)
            print(f"cluster up: gRPC {c.grpc}, dashboard {c.url}", flush=True)
            guarded("page loads", page_loads, d, c, artifacts)
            guarded("submit and image", submit_and_image, d, c, artifacts, dray, tmp)
            guarded("workers listed", workers_listed, d, c, artifacts)
            guarded("cancel", cancel_from_page, d, c, artifacts)
            guarded("download", download_from_page, d, c, artifacts)
            guarded("README screenshot", readme_screenshot, d, artifacts)
            # After the screenshot, which shows the newest finished job.
            guarded("frame range", frames_from_page, d, c, artifacts)
            guarded("many jobs", many_jobs, d, c, artifacts)
            c.stop()

            token_file = tmp / "api.token"
            token_file.write_text(base64.b64encode(hashlib.sha256(tmp_name.encode()).digest())
                                  .decode() + "\n")
            token_file.chmod(0o600)
            c = Cluster(dray, artifacts / "cluster-token.log", token_file=token_file)
            clusters.append(c)
            guarded("token", token_required, d, c, artifacts)
        finally:
            d.quit()
            for c in clusters:
                c.stop()
    total = time.monotonic() - started
    print(f"browser test: {len(passed)} passed, {len(failed)} failed, {len(skipped)} skipped "
          f"({total:.0f} s); "
          f"screenshots in {artifacts}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
