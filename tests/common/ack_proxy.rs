//! A TCP proxy in front of the server's HTTP port that loses acknowledgements on purpose: it
//! forwards every request, and for a random share of the `200` answers to `POST`s (batches)
//! it closes the client's connection instead of relaying the answer (the batch was applied,
//! its ack is lost). The upstream address can change (a restarted server listens on a new
//! port) or be absent (the server is down: connections are closed at once, as a refused
//! connection would be).
//!
//! One request per connection: the client must not pool connections (a dropped answer is
//! decided on the first bytes upstream sends after a connection opens).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use factord::factors::testing::Rng;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};

pub struct AckDroppingProxy {
    /// Where clients connect.
    pub addr: SocketAddr,
    shared: Arc<Shared>,
    task: tokio::task::JoinHandle<()>,
}

struct Shared {
    upstream: Mutex<Option<SocketAddr>>,
    rng: Mutex<Rng>,
    drop_rate: f64,
    /// `200` answers to `POST`s not relayed.
    dropped: AtomicU64,
    /// `200` answers to `POST`s relayed.
    relayed: AtomicU64,
    /// Connections closed because there was no server to forward to.
    refused: AtomicU64,
}

impl AckDroppingProxy {
    /// Listens on a free loopback port; drops `drop_rate` of the `200` answers (seeded).
    pub async fn start(seed: u64, drop_rate: f64) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("proxy binds");
        let addr = listener.local_addr().expect("proxy address");
        let shared = Arc::new(Shared {
            upstream: Mutex::new(None),
            rng: Mutex::new(Rng::new(seed)),
            drop_rate,
            dropped: AtomicU64::new(0),
            relayed: AtomicU64::new(0),
            refused: AtomicU64::new(0),
        });
        let s = Arc::clone(&shared);
        let task = tokio::spawn(async move {
            while let Ok((client, _)) = listener.accept().await {
                tokio::spawn(relay(client, Arc::clone(&s)));
            }
        });
        Self { addr, shared, task }
    }

    /// The server to forward to (`None`: the server is down).
    pub fn set_upstream(&self, upstream: Option<SocketAddr>) {
        *self.shared.upstream.lock().unwrap() = upstream;
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }

    /// `200` answers closed instead of relayed.
    pub fn dropped(&self) -> u64 {
        self.shared.dropped.load(Ordering::SeqCst)
    }

    pub fn relayed(&self) -> u64 {
        self.shared.relayed.load(Ordering::SeqCst)
    }

    pub fn refused(&self) -> u64 {
        self.shared.refused.load(Ordering::SeqCst)
    }
}

impl Drop for AckDroppingProxy {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn relay(mut client: TcpStream, shared: Arc<Shared>) {
    let upstream = *shared.upstream.lock().unwrap();
    let server = match upstream {
        Some(addr) => TcpStream::connect(addr).await.ok(),
        None => None,
    };
    let Some(server) = server else {
        shared.refused.fetch_add(1, Ordering::SeqCst);
        return; // dropping `client` closes it: the client sees a connection error
    };
    let (mut client_rx, mut client_tx) = client.split();
    let (mut server_rx, mut server_tx) = server.into_split();
    // Only the answers to batches (`POST`) are lost; status questions get theirs.
    let mut head = vec![0u8; 16 * 1024];
    let n = match client_rx.read(&mut head).await {
        Ok(0) | Err(_) => return,
        Ok(n) => n,
    };
    let droppable = head.starts_with(b"POST ");
    if server_tx.write_all(&head[..n]).await.is_err() {
        return;
    }
    let upload = async {
        let _ = tokio::io::copy(&mut client_rx, &mut server_tx).await;
        let _ = server_tx.shutdown().await;
    };
    let download = async {
        let mut first = vec![0u8; 16 * 1024];
        let n = match server_rx.read(&mut first).await {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        if droppable && first[..n].starts_with(b"HTTP/1.1 200") {
            let lose = shared.rng.lock().unwrap().uniform() < shared.drop_rate;
            if lose {
                shared.dropped.fetch_add(1, Ordering::SeqCst);
                return; // the answer is not relayed; the connection closes below
            }
            shared.relayed.fetch_add(1, Ordering::SeqCst);
        }
        if client_tx.write_all(&first[..n]).await.is_err() {
            return;
        }
        let _ = tokio::io::copy(&mut server_rx, &mut client_tx).await;
        let _ = client_tx.shutdown().await;
    };
    // The answer decides: once it is relayed (or lost) the connection is over.
    tokio::select! {
        _ = download => {}
        _ = async { upload.await; std::future::pending::<()>().await } => {}
    }
}
