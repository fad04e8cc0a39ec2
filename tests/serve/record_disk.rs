//! `--record DIR`: the recorder's accounting follows the disk, not its intentions. An old file
//! that cannot be removed stays counted, so `--record-max-bytes` holds on disk; a scene
//! directory removed from outside is made again and later batches are recorded.

use std::collections::BTreeSet;
use std::path::Path;
use std::time::Duration;

use crossview_data::read_recordings;
use crossview_serve::RecordConfig;
use crossview_testing::*;

/// Bytes of every file under `dir`, at any depth.
fn bytes_on_disk(dir: &Path) -> u64 {
    let mut total = 0;
    for e in std::fs::read_dir(dir).unwrap() {
        let e = e.unwrap();
        let meta = e.metadata().unwrap();
        total += if meta.is_dir() {
            bytes_on_disk(&e.path())
        } else {
            meta.len()
        };
    }
    total
}

/// Waits until `n` batches of `lab` reached the recording files.
async fn wait_recorded(server: &TestServer, n: f64) {
    let base = format!("http://{}", server.addr);
    wait_for_metric(&base, "crossview_record_batches_total{scene=\"lab\"}", n).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_old_file_that_cannot_be_removed_stays_counted_and_the_bound_holds_on_disk() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| {
        c.record = Some(RecordConfig {
            max_file_bytes: 2000,
            max_bytes: 6000,
            ..RecordConfig::new(&dir)
        });
    })
    .await;
    server.push_http(1..=8, 2).await;
    wait_recorded(&server, 24.0).await;
    // The oldest file becomes impossible to remove (even for root): a directory of that
    // name holding the same bytes.
    let mut names: Vec<_> = std::fs::read_dir(dir.join("lab"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    names.sort();
    let oldest = names[0].clone();
    let content = std::fs::read(&oldest).unwrap();
    std::fs::remove_file(&oldest).unwrap();
    std::fs::create_dir(&oldest).unwrap();
    std::fs::write(oldest.join("kept"), &content).unwrap();

    server.push_http(9..=60, 2).await;
    wait_recorded(&server, 180.0).await;
    let m = server.metrics().await;
    assert!(
        metric(&m, "crossview_record_files_removed_total") > 0.0,
        "{m}"
    );
    let gauge = metric(&m, "crossview_record_disk_bytes");
    assert!(gauge <= 6000.0, "gauge {gauge}");
    server.shutdown().await.unwrap();
    let on_disk = bytes_on_disk(&dir);
    assert!(
        on_disk <= 6000,
        "{on_disk} bytes on disk under a 6000-byte bound ({} kept in the stuck file)",
        content.len()
    );
    assert!(oldest.join("kept").exists());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_scene_directory_removed_while_running_is_made_again() {
    let rec_dir = tempfile::tempdir().unwrap();
    let dir = rec_dir.path().to_path_buf();
    let server = start(|c| c.record = Some(RecordConfig::new(&dir))).await;
    server.push_http(1..=10, 2).await;
    wait_recorded(&server, 30.0).await;
    std::fs::remove_dir_all(dir.join("lab")).unwrap();
    // Longer than the writer's reconciliation period, so the next batch sees the loss.
    tokio::time::sleep(Duration::from_millis(1200)).await;
    server.push_http(11..=40, 2).await;
    wait_recorded(&server, 120.0).await;
    let m = server.metrics().await;
    assert_eq!(
        metric(
            &m,
            "crossview_record_dropped_total{scene=\"lab\",reason=\"write_error\"}"
        ),
        0.0,
        "{m}"
    );
    server.shutdown().await.unwrap();
    let (rec, _) = read_recordings(&[&dir.join("lab")], true).unwrap();
    let got: BTreeSet<(String, u64)> = rec
        .batches()
        .map(|b| (b.camera.clone(), b.frame_id))
        .collect();
    for f in 11..=40 {
        for c in 0..3 {
            let cam = cameras()[c].name.clone();
            assert!(got.contains(&(cam.clone(), f)), "{cam} {f} not recorded");
        }
    }
    // The gauge followed the disk: the files of the removed directory left the books.
    assert!(bytes_on_disk(&dir) > 0);
}
