//! The browser console (`rigctl web`, docs/console.md) against a real `rigd --sim`: the
//! token gate over raw HTTP, then the page in Debian's headless Chromium driven through
//! WebDriver: the live view, a jog, a job from the form to its results and plots, pause,
//! resume and cancel, a fault and its unlock, a daemon restart. Screenshots of each step go
//! to target/tmp/web-console/. Without chromium and chromedriver the browser tests say
//! SKIPPED.

#![cfg(feature = "sim")]

use crate::support::skip::skipped;
use crate::support::web::{http, no_browser, Browser, Console};

fn get(c: &Console, path: &str, extra: &str) -> (u16, String) {
    let host = format!("Host: 127.0.0.1:{}", c.port);
    http(c.port, &format!("GET {path} HTTP/1.1\r\n{host}{extra}"), "")
}

fn post(c: &Console, path: &str, extra: &str, body: &str) -> (u16, String) {
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nContent-Type: application/json{extra}",
        c.port
    );
    http(c.port, &head, body)
}

const UPGRADE: &str = "\r\nConnection: Upgrade\r\nUpgrade: websocket\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==";

#[test]
fn every_request_needs_the_token_and_changes_need_it_in_a_header() {
    let c = Console::start(&[]);
    let t = &c.token;
    // The page: refused without the token or with a wrong one, served with it.
    let (s, body) = get(&c, "/", "");
    assert_eq!(s, 401, "{body}");
    assert!(body.contains("no token"), "{body}");
    assert_eq!(get(&c, "/?token=0123", "").0, 401);
    let (s, page) = get(&c, &format!("/?token={t}"), "");
    assert_eq!(s, 200);
    assert!(page.contains("rigd console") && page.contains(&format!("app.js?token={t}")));
    assert_eq!(get(&c, "/app.js", "").0, 401);
    // A request that changes anything: the token in the query is not enough.
    let hello = r#"{"kind": "hello"}"#;
    let (s, body) = post(&c, &format!("/api/request?token={t}"), "", hello);
    assert_eq!(s, 401);
    assert!(body.contains("X-Rigd-Token"), "{body}");
    let (s, body) = post(&c, "/api/request", &format!("\r\nX-Rigd-Token: {t}"), hello);
    assert_eq!(s, 200, "{body}");
    let reply: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(reply["ok"], true, "{reply}");
    assert_eq!(reply["result"]["protocol"], 1);
    // Subscriptions are the WebSocket's, not the API's; the refusal names the field.
    let sub = r#"{"kind": "subscribe"}"#;
    let (s, body) = post(&c, "/api/request", &format!("\r\nX-Rigd-Token: {t}"), sub);
    assert_eq!(s, 400);
    assert!(
        body.contains("`kind`") && body.contains("subscribe"),
        "{body}"
    );
    // The WebSocket: 401 without the token, switched with it.
    assert_eq!(get(&c, "/ws", UPGRADE).0, 401);
    assert_eq!(get(&c, &format!("/ws?token={t}"), UPGRADE).0, 101);
    // Another site's page, or a name rebound to loopback: 403, even with the token.
    let origin = format!("{UPGRADE}\r\nOrigin: http://evil.example");
    assert_eq!(get(&c, &format!("/ws?token={t}"), &origin).0, 403);
    let rebound = format!("GET /?token={t} HTTP/1.1\r\nHost: evil.example:{}", c.port);
    assert_eq!(http(c.port, &rebound, "").0, 403);
    // No CORS, ever; no referrer leaves with the token.
    let head = format!("GET /?token={t} HTTP/1.1\r\nHost: 127.0.0.1:{}", c.port);
    let mut s = std::net::TcpStream::connect(("127.0.0.1", c.port)).unwrap();
    use std::io::{Read, Write};
    write!(s, "{head}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = String::new();
    s.read_to_string(&mut raw).unwrap();
    let lower = raw.to_ascii_lowercase();
    assert!(!lower.contains("access-control-allow"), "{raw}");
    assert!(lower.contains("referrer-policy: no-referrer"), "{raw}");
}

/// Run `f` with a browser on a console, or say SKIPPED.
fn with_browser<F, Fut>(test: &str, console: Console, f: F)
where
    F: FnOnce(Browser, Console) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    if let Some(why) = no_browser() {
        skipped(test, &why);
        return;
    }
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async move {
        let b = Browser::start().await;
        f(b, console).await;
    });
}

#[test]
fn the_page_shows_the_live_view_jogs_and_survives_a_daemon_restart() {
    let test = "the_page_shows_the_live_view_jogs_and_survives_a_daemon_restart";
    with_browser(test, Console::start(&[]), |b, mut c| async move {
        // Without the token the browser gets the refusal, not the page.
        b.client.goto(&format!("{}/", c.base)).await.unwrap();
        let text = b.js("document.body.innerText").await;
        assert!(text.as_str().unwrap().contains("no token"), "{text}");
        b.client.goto(&c.url()).await.unwrap();
        b.until("window.rig && rig.frames >= 3", 30).await;
        // The picture follows the camera: newer frames, another image.
        let (seq, src) = (
            b.js("rig.paintedSequence").await,
            b.js("document.getElementById('frame').src").await,
        );
        b.until(&format!("rig.paintedSequence > {seq}"), 10).await;
        assert_ne!(b.js("document.getElementById('frame').src").await, src);
        b.until(
            "document.querySelectorAll('#overlay circle').length >= 2",
            10,
        )
        .await;
        b.screenshot("01-live-view").await;
        // A jog: the stage moves by the step and the shown position follows.
        b.until("!document.getElementById('jog-axis-plus').disabled", 10)
            .await;
        let pos = "parseFloat(document.getElementById('pos-axis').textContent)";
        b.until(&format!("!isNaN({pos})"), 10).await;
        let before = b.js(pos).await.as_f64().unwrap();
        b.set("jog-step", "500").await;
        b.click("#jog-axis-plus").await;
        let want = before + 500.0;
        b.until(&format!("Math.abs({pos} - {want}) < 1"), 20).await;
        b.screenshot("02-jogged").await;
        // The daemon restarts: the page says so within 2 s and reconnects by itself.
        c.kill_rigd();
        b.until("rig.daemon !== 'up'", 2).await;
        b.screenshot("03-daemon-gone").await;
        let frames = b.js("rig.frames").await.as_u64().unwrap();
        c.start_rigd();
        b.until("rig.daemon === 'up'", 10).await;
        b.until(&format!("rig.frames > {frames} + 3"), 20).await;
        b.screenshot("04-reconnected").await;
    });
}

#[test]
fn a_job_from_the_form_runs_and_its_results_and_plots_appear() {
    let test = "a_job_from_the_form_runs_and_its_results_and_plots_appear";
    with_browser(test, Console::start(&[]), |b, c| async move {
        b.client.goto(&c.url()).await.unwrap();
        b.until("rig.state && rig.state.state === 'ready'", 30)
            .await;
        // A field the daemon refuses: its message beside that field.
        b.set("f-steps", "3").await;
        b.set("f-k", "99").await;
        b.click("#f-submit").await;
        let err = b
            .until(
                "document.querySelector('.err[data-field=\"k\"]').textContent",
                10,
            )
            .await;
        assert!(err.as_str().unwrap().contains("99"), "{err}");
        b.screenshot("05-form-error").await;
        // A good one: queued, its progress advances, and it ends with its results.
        b.set("f-k", "2").await;
        b.set("f-steps", "8").await;
        b.set("f-step_um", "100").await;
        b.set("f-settle_ms", "200").await;
        b.click("#f-submit").await;
        b.until(
            "document.getElementById('f-ok').textContent.includes('queued')",
            10,
        )
        .await;
        let done = "document.querySelector('#queue .job-frames')";
        b.until(&format!("{done} && parseInt({done}.textContent) >= 1"), 30)
            .await;
        b.screenshot("06-job-running").await;
        b.until(&format!("{done} && parseInt({done}.textContent) >= 4"), 30)
            .await;
        b.until("document.querySelector('#sessions tr[data-session]') && document.querySelector('#sessions tr[data-session]').textContent.includes('finished')", 120)
            .await;
        b.click("#sessions tr[data-session]").await;
        let rows = b
            .until("document.querySelectorAll('#targets tbody tr').length", 30)
            .await;
        assert!(rows.as_u64().unwrap() >= 2, "{rows} target rows");
        let table = b.js("document.getElementById('targets').innerText").await;
        assert!(table.as_str().unwrap().contains('±'), "{table}");
        // Every chart drawn: the residuals, the offsets with u, loaded as images.
        b.until("[...document.querySelectorAll('#charts img')].length >= 2 && [...document.querySelectorAll('#charts img')].every(i => i.complete && i.naturalWidth > 0)", 30)
            .await;
        let alts = b
            .js("[...document.querySelectorAll('#charts img')].map(i => i.alt).join(' ')")
            .await;
        assert!(alts.as_str().unwrap().contains("residuals"), "{alts}");
        assert!(alts.as_str().unwrap().contains("offsets"), "{alts}");
        b.screenshot("07-results").await;
        // The download is the session's results.csv.
        let href = b
            .js("document.getElementById('dl-csv').getAttribute('href')")
            .await;
        let (s, csv) = http(
            c.port,
            &format!(
                "GET {} HTTP/1.1\r\nHost: 127.0.0.1:{}",
                href.as_str().unwrap(),
                c.port
            ),
            "",
        );
        assert_eq!(s, 200);
        assert!(csv.starts_with("run,case,repeat,target"), "{csv}");
        // The frames as OME-TIFF, fetched as the page's link does: a little-endian TIFF
        // with its OME-XML, every frame in it (8 planes of 3 channels, 1280x720).
        b.js("(window.dl = null, fetch(document.getElementById('dl-tiff').href).then(r => r.arrayBuffer().then(b => { const u = new Uint8Array(b); window.dl = {status: r.status, type: r.headers.get('content-type'), bytes: u.length, head: String.fromCharCode(u[0], u[1]), ome: new TextDecoder('latin1').decode(u.subarray(0, 65536)).includes('OME')}; })), true)")
            .await;
        let dl = b.until("window.dl", 60).await;
        assert_eq!(dl["status"], 200, "{dl}");
        assert_eq!(dl["type"], "image/tiff", "{dl}");
        assert_eq!(dl["head"], "II", "{dl}");
        assert_eq!(dl["ome"], true, "{dl}");
        assert!(dl["bytes"].as_u64().unwrap() >= 8 * 3 * 1280 * 720, "{dl}");
        // A session that is not there: named, not a server error.
        let (s, body) = get(
            &c,
            &format!("/files/nope/export.ome.tif?token={}", c.token),
            "",
        );
        assert_eq!(s, 404, "{body}");
        assert!(body.contains("nope"), "{body}");
    });
}

#[test]
fn pause_resume_and_cancel_work_from_the_page() {
    let test = "pause_resume_and_cancel_work_from_the_page";
    with_browser(test, Console::start(&[]), |b, c| async move {
        b.client.goto(&c.url()).await.unwrap();
        b.until("rig.state && rig.state.state === 'ready'", 30)
            .await;
        b.set("f-steps", "200").await;
        b.set("f-step_um", "50").await;
        b.set("f-settle_ms", "100").await;
        b.click("#f-process").await; // capture only
        b.click("#f-submit").await;
        b.until("document.querySelector('#queue .job-pause')", 20)
            .await;
        b.click("#queue .job-pause").await;
        b.until("document.querySelector('#queue .job-state') && document.querySelector('#queue .job-state').textContent === 'paused'", 20)
            .await;
        // Paused: the frame count stands still. (The step under way when the pause came
        // may still report its frame just after the page shows `paused`.)
        let frames = "parseInt(document.querySelector('#queue .job-frames').textContent)";
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
        let at = b.js(frames).await;
        tokio::time::sleep(std::time::Duration::from_millis(800)).await;
        assert_eq!(b.js(frames).await, at);
        b.screenshot("08-paused").await;
        b.click("#queue .job-resume").await;
        b.until(&format!("document.querySelector('#queue .job-state').textContent === 'running' && {frames} > {at}"), 20)
            .await;
        b.click("#queue .job-cancel").await;
        b.until("document.querySelector('#sessions tr[data-session]') && document.querySelector('#sessions tr[data-session]').textContent.includes('cancelled')", 30)
            .await;
        b.until("!document.querySelector('#queue .job-cancel')", 10)
            .await;
        b.screenshot("09-cancelled").await;
    });
}

#[test]
fn a_fault_shows_with_its_reason_and_unlock_clears_it() {
    let test = "a_fault_shows_with_its_reason_and_unlock_clears_it";
    // The axis raises a hard-limit alarm on its first move.
    with_browser(
        test,
        Console::start(&["--fault", "alarm@1"]),
        |b, c| async move {
            b.client.goto(&c.url()).await.unwrap();
            b.until("rig.state && rig.state.state === 'ready'", 30)
                .await;
            assert_eq!(
                b.js("document.getElementById('unlock').disabled").await,
                true
            );
            b.set("jog-step", "200").await;
            b.click("#jog-axis-plus").await;
            b.until("rig.state && rig.state.state === 'fault'", 20)
                .await;
            let badge = b.until("document.getElementById('rig-state').className.includes('fault') && document.getElementById('rig-reason').textContent", 10).await;
            assert!(badge.as_str().unwrap().contains("axis"), "{badge}");
            // Jogging is refused, with the reason; unlock is offered.
            b.until("document.getElementById('jog-axis-plus').disabled", 10)
                .await;
            let why = b.js("document.getElementById('jog-axis-plus').title").await;
            assert!(why.as_str().unwrap().contains("fault"), "{why}");
            b.until("!document.getElementById('unlock').disabled", 10)
                .await;
            b.screenshot("10-fault").await;
            b.click("#unlock").await;
            b.until("rig.state && rig.state.state === 'ready' && !document.getElementById('jog-axis-plus').disabled", 20)
            .await;
            b.screenshot("11-unlocked").await;
        },
    );
}

/// Pick `plan` in the form as a person does: the select changed, its change event fired.
async fn choose_plan(b: &Browser, plan: &str) {
    b.set("f-plan", plan).await;
    b.js("document.getElementById('f-plan').dispatchEvent(new Event('change')), true")
        .await;
}

/// Whether the form row of class `class` shows.
fn row_shows(class: &str) -> String {
    format!("!document.querySelector('#job-form .{class}').hidden")
}

#[test]
fn grid_and_list_plans_from_the_form_run_and_their_errors_show_beside_their_fields() {
    let test = "grid_and_list_plans_from_the_form_run_and_their_errors_show_beside_their_fields";
    let ideal = Console::start(&["--camera", "ideal"]);
    with_browser(test, ideal, |b, c| async move {
        b.client.goto(&c.url()).await.unwrap();
        b.until("rig.state && rig.state.state === 'ready'", 30)
            .await;
        // A grid: its two lines show, the line's fields hide.
        choose_plan(&b, "grid").await;
        assert_eq!(b.js(&row_shows("plan-grid")).await, true);
        assert_eq!(b.js(&row_shows("plan-scan")).await, false);
        // A step the daemon refuses on the piezo: its message beside the outer line.
        b.set("f-outer-step_um", "1e9").await;
        b.click("#f-submit").await;
        let err = "document.querySelector('.err[data-field=\"plan.grid.outer\"]').textContent";
        let said = b.until(err, 10).await;
        assert!(said.as_str().unwrap().contains("plan.grid.outer"), "{said}");
        b.screenshot("12-grid-error").await;
        // The form's own grid, 4 x 3, runs to its end.
        b.set("f-outer-step_um", "100").await;
        b.set("f-settle_ms", "0").await;
        b.click("#f-submit").await;
        let ok = "document.getElementById('f-ok').textContent";
        let queued = b
            .until(&format!("{ok}.includes('queued') && {ok}"), 10)
            .await;
        assert!(queued.as_str().unwrap().contains("(12 frames)"), "{queued}");
        let finished = "document.querySelector('#sessions tr[data-session]') && document.querySelector('#sessions tr[data-session]').textContent.includes('finished')";
        b.until(finished, 60).await;
        b.screenshot("13-grid-finished").await;
        // A list: a line that is no position is named by the page, before anything is sent.
        choose_plan(&b, "list").await;
        assert_eq!(b.js(&row_shows("plan-list")).await, true);
        b.set("f-list", "1000\n1200, x").await;
        b.click("#f-submit").await;
        let err = "document.querySelector('.err[data-field=\"plan.list\"]').textContent";
        let said = b.until(err, 10).await;
        assert!(said.as_str().unwrap().contains("plan.list[1]"), "{said}");
        // A position beyond the axis's soft limits: the daemon's refusal, beside the list.
        b.set("f-list", "1000\n1e12").await;
        b.click("#f-submit").await;
        let said = b.until(err, 10).await;
        assert!(said.as_str().unwrap().contains("plan.list"), "{said}");
        b.screenshot("14-list-error").await;
        b.set("f-list", "1000\n1400\n1800, 300").await;
        b.click("#f-submit").await;
        let queued = b
            .until(&format!("{ok}.includes('queued') && {ok}"), 10)
            .await;
        assert!(queued.as_str().unwrap().contains("(3 frames)"), "{queued}");
    });
}

#[test]
fn the_calibration_panel_shows_the_record_a_job_from_its_button_makes() {
    let test = "the_calibration_panel_shows_the_record_a_job_from_its_button_makes";
    let ideal = Console::start(&["--camera", "ideal"]);
    with_browser(test, ideal, |b, c| async move {
        b.client.goto(&c.url()).await.unwrap();
        b.until("rig.state && rig.state.state === 'ready'", 30)
            .await;
        let record = "document.getElementById('cal-record').textContent";
        let none = b.until(&format!("{record} !== '–' && {record}"), 10).await;
        assert_eq!(none, "no current calibration");
        b.click("#cal-run").await;
        let msg = b
            .until("document.getElementById('cal-msg').textContent", 10)
            .await;
        assert!(msg.as_str().unwrap().contains("calibration job"), "{msg}");
        // The scan's 40 frames and the fit, then the record the page reads back.
        let made = b
            .until(
                &format!("{record}.includes('field residual') && {record}"),
                120,
            )
            .await;
        let made = made.as_str().unwrap();
        assert!(made.starts_with("cal-"), "{made}");
        assert!(
            made.contains("(0.0 days old)") && made.contains("40 frames 500 µm apart"),
            "{made}"
        );
        b.screenshot("15-calibrated").await;
    });
}
