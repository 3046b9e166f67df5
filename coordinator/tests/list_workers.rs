//! ListWorkers in pages (issue 45, item 8), over real gRPC against a live coordinator
//! with workers registered through ClusterService: walking `next_page_token` lists
//! every worker exactly once, also when a worker already listed leaves mid-walk; the
//! running jobs' tables come on the first page only; a bad token is INVALID_ARGUMENT;
//! a page holds at most 1000 workers, and the dashboard walks the pages.

mod support;

use std::collections::BTreeSet;
use std::time::Instant;

use dray_coordinator::http::Dashboard;
use dray_proto::v1::cluster_service_client::ClusterServiceClient;
use dray_proto::v1::render_service_client::RenderServiceClient;
use dray_proto::v1::{ListWorkersRequest, ListWorkersResponse};
use tonic::Code;
use tonic::transport::Channel;

use support::*;

/// Register `n` workers through RegisterWorker (no assignment streams: listing needs
/// none); their ids.
async fn register(channel: &Channel, n: usize) -> Vec<String> {
    let mut ids = Vec::with_capacity(n);
    for k in 0..n {
        let mut c = ClusterServiceClient::new(channel.clone());
        let r = c
            .register_worker(register_request(&format!(
                "http://127.0.0.1:{}",
                10_000 + k
            )))
            .await
            .expect("RegisterWorker")
            .into_inner();
        ids.push(r.worker_id);
    }
    ids
}

/// One ListWorkers page.
async fn page(
    channel: &Channel,
    page_size: u32,
    page_token: &str,
) -> Result<ListWorkersResponse, tonic::Status> {
    RenderServiceClient::new(channel.clone())
        .list_workers(ListWorkersRequest {
            omit_jobs: false,
            page_size,
            page_token: page_token.into(),
        })
        .await
        .map(|r| r.into_inner())
}

/// Every page from the first, with `between(k)` run after page `k` was received.
async fn walk(
    channel: &Channel,
    page_size: u32,
    mut between: impl FnMut(usize, &ListWorkersResponse),
) -> Vec<ListWorkersResponse> {
    let mut pages: Vec<ListWorkersResponse> = Vec::new();
    let mut token = String::new();
    loop {
        let p = page(channel, page_size, &token).await.expect("ListWorkers");
        between(pages.len(), &p);
        token = p.next_page_token.clone();
        pages.push(p);
        if token.is_empty() {
            return pages;
        }
        assert!(pages.len() <= 1000, "the walk does not end");
    }
}

fn ids_of(pages: &[ListWorkersResponse]) -> Vec<String> {
    pages
        .iter()
        .flat_map(|p| p.workers.iter().map(|w| w.worker_id.clone()))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pages_list_every_worker_exactly_once() {
    let server = Server::start("list-pages", slow_heartbeat()).await;
    let channel = server.channel().await;
    let registered: BTreeSet<String> = register(&channel, 25).await.into_iter().collect();

    // 25 workers by 7: 7, 7, 7, 4, each worker once, in id order.
    let pages = walk(&channel, 7, |_, _| {}).await;
    let sizes: Vec<usize> = pages.iter().map(|p| p.workers.len()).collect();
    assert_eq!(sizes, [7, 7, 7, 4]);
    let listed = ids_of(&pages);
    let mut sorted = listed.clone();
    sorted.sort();
    assert_eq!(listed, sorted, "pages are in id order");
    assert_eq!(
        listed.len(),
        registered.len(),
        "no worker twice: {listed:?}"
    );
    assert_eq!(listed.into_iter().collect::<BTreeSet<_>>(), registered);
    // A page size that divides the count: the last full page says there is no next.
    let pages = walk(&channel, 5, |_, _| {}).await;
    assert_eq!(pages.len(), 5);
    assert_eq!(ids_of(&pages).len(), 25);

    // The default page (0: 100 workers) holds them all, and says it is the last.
    let all = page(&channel, 0, "").await.expect("ListWorkers");
    assert_eq!(all.workers.len(), 25);
    assert!(all.next_page_token.is_empty());

    // A worker already listed leaves during the walk: every worker that stays is
    // still listed once (a cursor by position would skip the one that moved up into
    // the page already sent).
    let membership = server.coordinator.cluster().membership.clone();
    let mut gone = None;
    let pages = walk(&channel, 7, |k, p| {
        if k == 0 {
            let first = p.workers[0].worker_id.clone();
            assert!(
                membership
                    .drop_unreachable(&first, "the test", Instant::now())
                    .is_some()
            );
            gone = Some(first);
        }
    })
    .await;
    let gone = gone.expect("a worker left");
    let listed = ids_of(&pages);
    let stayed: BTreeSet<String> = registered.iter().filter(|w| **w != gone).cloned().collect();
    for w in &stayed {
        assert_eq!(
            listed.iter().filter(|l| *l == w).count(),
            1,
            "{w} in {listed:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_bad_page_token_is_invalid_argument() {
    let server = Server::start("list-bad-token", slow_heartbeat()).await;
    let channel = server.channel().await;
    register(&channel, 3).await;
    for bad in [
        "2",
        "garbage",
        "w1-",
        "w-0000abcd",
        "w1-zzzzzzzz",
        "w1-0000abcd0",
    ] {
        let e = page(&channel, 1, bad)
            .await
            .expect_err("a token this server never gives");
        assert_eq!(e.code(), Code::InvalidArgument, "{bad}: {e:?}");
        assert!(e.message().contains("page_token"), "{bad}: {}", e.message());
    }
    // A token of a worker that is gone (or of an earlier coordinator) is still a place
    // in id order: the workers after it.
    let first = page(&channel, 1, "").await.expect("the first page");
    assert!(!first.next_page_token.is_empty());
    let rest = page(&channel, 10, "w0-00000000")
        .await
        .expect("a place in order");
    assert_eq!(rest.workers.len(), 3);
}

/// The jobs' domain tables are the cluster's, not a page's: on the first page only.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn running_jobs_come_with_the_first_page_only() {
    let server = Server::start("list-jobs-first", slow_heartbeat()).await;
    let channel = server.channel().await;
    let mut a = FakeWorker::join(channel.clone(), "http://127.0.0.1:7001").await;
    let mut b = FakeWorker::join(channel.clone(), "http://127.0.0.1:7002").await;
    let id = submit(&channel, spec(70, 40, 3)).await;
    // Both workers are in the job once each has its setup.
    for w in [&mut a, &mut b] {
        loop {
            if let dray_proto::v1::assignment::Command::Setup(s) = w.next().await {
                assert_eq!(s.job_id, id);
                break;
            }
        }
    }
    let pages = walk(&channel, 1, |_, _| {}).await;
    assert_eq!(pages.len(), 2);
    assert_eq!(pages[0].jobs.len(), 1, "{:?}", pages[0].jobs);
    assert_eq!(pages[0].jobs[0].job_id, id);
    assert_eq!(pages[0].jobs[0].domains.len(), 3);
    assert!(pages[1].jobs.is_empty(), "{:?}", pages[1].jobs);
    // Each page's worker still shows its job and its own domains of it, and the two
    // own the three domains between them.
    let mut owned = Vec::new();
    for p in &pages {
        let w = &p.workers[0];
        assert_eq!(w.jobs, std::slice::from_ref(&id), "{w:?}");
        assert!(w.domains.iter().all(|d| d.job_id == id), "{w:?}");
        owned.extend(w.domains.iter().filter(|d| d.owned).map(|d| d.domain));
    }
    owned.sort();
    assert_eq!(owned, [0, 1, 2]);
}

/// A page is at most 1000 workers whatever is asked; the dashboard's `/api/workers`
/// walks the pages and shows every worker.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pages_hold_at_most_1000_and_the_dashboard_walks_them() {
    let server = Server::start("list-max-page", slow_heartbeat()).await;
    let channel = server.channel().await;
    let registered: BTreeSet<String> = register(&channel, 1003).await.into_iter().collect();
    let first = page(&channel, 5000, "").await.expect("ListWorkers");
    assert_eq!(first.workers.len(), 1000);
    assert!(!first.next_page_token.is_empty());
    let dashboard = Dashboard::new(server.coordinator.clone(), None).expect("dashboard");
    let shown = dashboard.workers().await.expect("the dashboard's workers");
    let ids: Vec<String> = shown.workers.iter().map(|w| w.id.clone()).collect();
    assert_eq!(ids.len(), 1003);
    assert_eq!(ids.into_iter().collect::<BTreeSet<_>>(), registered);
}
