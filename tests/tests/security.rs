//! Who may use a farm, in one process: a client without the client token (or with a wrong
//! one) is refused with `UNAUTHENTICATED` and a message naming the flag, and with it renders
//! the local image; a worker without the worker token never registers and says why; a `Cast`
//! stream without it is refused by the worker itself; a whole render over TLS matches local
//! mode byte for byte; a worker refuses the stream over its cap, and a job waits for room
//! instead of failing. Certificates are made here at run time: no key is ever committed.

use std::path::Path;
use std::time::Duration;

use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use trove_coordinator::client::{ClientError, FarmClient};
use trove_core::render::{render, RenderOptions};
use trove_core::scene::{DataRoot, Scene};
use trove_proto::auth::Token;
use trove_proto::connect::Connector;
use trove_proto::tls::{CaCert, ServerTls};
use trove_proto::v1 as pb;
use trove_proto::v1::worker_client::WorkerClient;
use trove_tests::farm::{FarmOptions, TestFarm, TestTls};
use trove_tests::scenes::{self, SLAB_AND_BALL as SCENE};
use trove_tests::scratch;
use trove_tests::tls::TestPki;
use trove_worker::WorkerError;

/// A scene of generated data only: any worker casts it.
const GENERATED: &str = r#"
[image]
width = 32
height = 32
background = [0.1, 0.1, 0.2]
[camera]
eye = [0.5, 0.6, 3.0]
target = [0.5, 0.5, 0.5]
up = [0, 1, 0]
fov_y = 35.0
[[datasets]]
name = "ball"
dims = [24, 24, 24]
[datasets.channels.voxel]
generator = { kind = "sphere", radius = 0.5, profile = "radial", value = 1.0, type = "f32" }
[[objects]]
name = "ball"
dataset = "ball"
colour = { type = "ramp", points = [[0.0, 0.9, 0.3, 0.1], [1.0, 0.2, 0.5, 1.0]] }
opacity = { type = "ramp", points = [[0.0, 0.0], [1.0, 0.3]] }
"#;

/// The slab's data root.
fn slab_root(dir: &Path) -> std::path::PathBuf {
    scenes::slab_root(&dir.join("w0"))
}

/// What local mode renders from `text` with its keys under `data`.
fn local_png(text: &str, data: &Path) -> Vec<u8> {
    let scene = Scene::parse_in(text, "scene.toml", &DataRoot::Given(data.to_path_buf())).unwrap();
    render(&scene, &RenderOptions::default()).unwrap().image.encode_png().unwrap()
}

fn token(text: &str) -> Option<Token> {
    Some(Token::new(text).unwrap())
}

/// A CA, and one certificate it signed for 127.0.0.1 and localhost, made now.
fn test_tls() -> TestTls {
    let pki = TestPki::new();
    TestTls {
        ca: CaCert::from_pem(pki.ca.as_bytes()).unwrap(),
        server: ServerTls::from_pem(pki.cert.as_bytes(), pki.key.as_bytes()).unwrap(),
    }
}

/// A `Cast` request stream whose first message opens `scene` for dataset 0, with its sender
/// (the stream stays open while the sender lives).
fn open_stream(scene: &str) -> (mpsc::Sender<pb::CastRequest>, ReceiverStream<pb::CastRequest>) {
    let (tx, rx) = mpsc::channel(4);
    let open = pb::CastOpen {
        job_id: "by-hand".into(),
        scene_toml: scene.into(),
        scene_name: "scene.toml".into(),
        dataset: 0,
        headers: Vec::new(),
        scene_digest: Vec::new(),
        shadow_maps: Vec::new(),
        shadow_maps_computed: false,
    };
    tx.try_send(pb::CastRequest { kind: Some(pb::cast_request::Kind::Open(open)) }).unwrap();
    (tx, ReceiverStream::new(rx))
}

#[test]
fn a_client_without_the_client_token_is_refused_and_with_it_renders_the_local_image() {
    let dir = scratch("security-client");
    let root = slab_root(&dir);
    let options = FarmOptions {
        client_token: token("client-secret"),
        worker_token: token("worker-secret"),
        ..Default::default()
    };
    let farm = TestFarm::start_opts(std::slice::from_ref(&root), options);
    let refused = |connector: Connector| {
        farm.block_on(async {
            let mut client =
                FarmClient::connect_with(&farm.url, &connector).await.expect("the connection itself is open");
            client.render(SCENE.into(), "scene.toml".into(), pb::JobOptions::default(), |_| {}).await.unwrap_err()
        })
    };
    // No token, a wrong one, and the worker token (a secret of its own) are all refused.
    for (connector, sent) in [
        (Connector::default(), false),
        (Connector::new(None, token("client-secreT")), true),
        (Connector::new(None, token("worker-secret")), true),
    ] {
        let e = refused(connector);
        assert!(matches!(e, ClientError::Unauthenticated { sent: s, .. } if s == sent), "{e:?}");
        let message = e.to_string();
        assert!(message.contains("refused") && message.contains("--token-file"), "{message}");
    }
    let files = farm.render(SCENE, "scene.toml", false).expect("the right token renders");
    assert!(files.png == local_png(SCENE, &root), "the farm's PNG differs from local mode's");
}

#[test]
fn a_worker_without_the_worker_token_never_registers_and_says_why() {
    let dir = scratch("security-worker");
    let root = slab_root(&dir);
    let options = FarmOptions { worker_token: token("worker-secret"), ..Default::default() };
    let mut farm = TestFarm::start_opts(&[], options);
    for presented in [None, token("not-the-worker-secret")] {
        let mut config = farm.worker_config(&root, None);
        config.security.token = presented.clone();
        let ran = farm.block_on(async {
            let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
            let run = trove_worker::run(listener, std::future::pending(), config);
            tokio::time::timeout(Duration::from_secs(20), run).await
        });
        let e = ran.expect("a refused worker stops by itself").expect_err("a worker without the token cannot run");
        assert!(matches!(e, WorkerError::Refused(_)), "{e:?}");
        let message = e.to_string();
        assert!(message.contains("--token-file") && message.contains("--worker-token-file"), "{message}");
        assert!(farm.worker_addresses().is_empty(), "a worker registered with {presented:?}");
    }
    // With the token it registers and serves.
    farm.add_worker(&root, None);
    farm.wait_for_workers(1);
    let files = farm.render(SCENE, "scene.toml", false).unwrap();
    assert!(files.png == local_png(SCENE, &root));
}

#[test]
fn a_cast_stream_without_the_worker_token_is_refused_by_the_worker() {
    let dir = scratch("security-cast");
    let root = slab_root(&dir);
    let options = FarmOptions { worker_token: token("worker-secret"), ..Default::default() };
    let farm = TestFarm::start_opts(std::slice::from_ref(&root), options);
    let address = farm.worker_addresses().pop().expect("one worker");
    for presented in [None, token("guess")] {
        let code = farm.block_on(async {
            let connector = Connector::new(None, presented);
            let endpoint = connector.endpoint(&format!("http://{address}")).unwrap();
            let mut client = WorkerClient::new(connector.connect(endpoint).await.unwrap());
            let (_tx, stream) = open_stream(GENERATED);
            client.cast(stream).await.map(|_| ()).unwrap_err().code()
        });
        assert_eq!(code, tonic::Code::Unauthenticated);
    }
    // The coordinator presents the token on its own streams, so jobs still run.
    let files = farm.render(SCENE, "scene.toml", false).unwrap();
    assert!(files.png == local_png(SCENE, &root));
}

#[test]
fn a_whole_render_over_tls_matches_local_mode_and_plaintext_or_a_stranger_ca_is_refused() {
    let dir = scratch("security-tls");
    let root = slab_root(&dir);
    let options = FarmOptions {
        client_token: token("client-secret"),
        worker_token: token("worker-secret"),
        tls: Some(test_tls()),
        ..Default::default()
    };
    let roots = [root.clone(), slab_root(&dir.join("second"))];
    let farm = TestFarm::start_opts(&roots, options);
    assert!(farm.url.starts_with("https://127.0.0.1:"), "{}", farm.url);
    let files = farm.render(SCENE, "scene.toml", false).expect("a render over TLS");
    assert!(files.png == local_png(SCENE, &root), "the farm's PNG over TLS differs from local mode's");
    // Plaintext to a TLS port, and TLS verified against a CA that did not sign the
    // coordinator's certificate, both fail before any job is taken.
    let plaintext = farm.url.replace("https://", "http://");
    let stranger = Connector::new(Some(test_tls().ca), token("client-secret"));
    for (url, connector) in [(plaintext.as_str(), Connector::new(None, token("client-secret"))), (&farm.url, stranger)]
    {
        let refused = farm.block_on(async {
            let call = async {
                let mut client = FarmClient::connect_with(url, &connector).await?;
                client.workers().await
            };
            tokio::time::timeout(Duration::from_secs(20), call).await.expect("refused within the deadline")
        });
        assert!(refused.is_err(), "{url}: a call without TLS or with the wrong CA was served");
    }
}

#[test]
fn a_worker_refuses_the_stream_over_its_cap_and_a_job_waits_for_room_instead_of_failing() {
    let dir = scratch("security-cap");
    let root = dir.join("w0");
    std::fs::create_dir_all(&root).unwrap();
    let options = FarmOptions { max_streams: 1, ..Default::default() };
    let farm = TestFarm::start_opts(std::slice::from_ref(&root), options);
    let address = farm.worker_addresses().pop().expect("one worker");
    let (held, status) = farm.block_on(async {
        let mut client = WorkerClient::connect(format!("http://{address}")).await.unwrap();
        // The one stream the worker serves, held open; one more is refused.
        let (tx, stream) = open_stream(GENERATED);
        let response = client.cast(stream).await.expect("the first stream is served");
        let (_tx2, stream) = open_stream(GENERATED);
        let refused = client.cast(stream).await.map(|_| ()).unwrap_err();
        ((tx, response), refused)
    });
    assert_eq!(status.code(), tonic::Code::ResourceExhausted);
    assert!(status.message().contains("--max-streams"), "{}", status.message());

    // A job now finds its only holder busy. It waits (a refused stream costs its batches
    // no attempt, so it does not run out of them) and completes once the room is free.
    let (jobs, id) = farm.block_on(async {
        let mut client = farm.client().await;
        let id = client.submit(GENERATED.into(), "scene.toml".into(), pb::JobOptions::default()).await.unwrap();
        (client, id)
    });
    let mut jobs = jobs;
    // Long enough for many refusals at the test heartbeat (100 ms): more than the job's
    // five attempts per batch would allow if refusals counted, and than a lost holder's
    // rest, after which a job with no holder left fails.
    let waited =
        farm.block_on(async { tokio::time::timeout(Duration::from_millis(1500), jobs.watch(&id, |_| {})).await });
    assert!(waited.is_err(), "the job ended while its only holder was busy: {waited:?}");
    drop(held);
    let last = farm.block_on(async {
        tokio::time::timeout(Duration::from_secs(60), jobs.watch(&id, |_| {})).await.expect("the job ends")
    });
    let last = last.unwrap();
    assert_eq!(last.state(), pb::JobState::Succeeded, "{:?}", last.failure);
    let files = farm.block_on(jobs.result(&id)).unwrap();
    assert!(files.png == local_png(GENERATED, &root));
}
