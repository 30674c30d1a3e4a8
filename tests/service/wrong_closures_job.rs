//! A batch job over HTTP with wrong loop closures (issue 54, item 3): `outliers=auto` rejects
//! exactly the wrong closures and ends at the clean file's optimum; the default is plain least
//! squares; an unknown mode is refused naming the parameter (catalogue J84).

use crate::common;
use common::server::{client, post_raw, TestServer};
use common::wrong_closures::{add_random_wrong_closures, label_lines};

#[tokio::test(flavor = "multi_thread")]
async fn a_job_rejects_wrong_closures_and_refuses_an_unknown_mode() {
    let Some(file) = common::data_file("2d/carlone/input_M3500_g2o.g2o") else {
        return;
    };
    let s = TestServer::start(&["--no-zenoh"]);
    let c = client();
    let clean = std::fs::read_to_string(&file).unwrap();
    let (corrupted, _, wrong) = add_random_wrong_closures(&clean, 0.2, 7);

    let auto = s.url("/v1/jobs?outliers=auto");
    let (status, plain) = post_raw(&c, &auto, clean.clone()).await;
    assert_eq!(status, 200, "{plain}");
    assert_eq!(
        plain["outliers"]["graduated"], false,
        "{}",
        plain["outliers"]
    );
    let clean_chi2 = plain["summary"]["final_chi2"].as_f64().unwrap();

    let (status, robust) = post_raw(&c, &auto, corrupted.clone()).await;
    assert_eq!(status, 200, "{robust}");
    assert_eq!(label_lines(&robust["outliers"]["rejected_labels"]), wrong);
    let chi2 = robust["summary"]["final_chi2"].as_f64().unwrap();
    assert!(
        (chi2 - clean_chi2).abs() <= 1e-5 * clean_chi2,
        "{chi2} vs {clean_chi2}"
    );
    // Same gauge (pose 0 held): the estimates compare value by value.
    let (a, b) = (
        plain["estimate"]["variables"].as_array().unwrap(),
        robust["estimate"]["variables"].as_array().unwrap(),
    );
    assert_eq!(a.len(), b.len());
    let mut squared = 0.0;
    for (a, b) in a.iter().zip(b) {
        assert_eq!(a["key"], b["key"]);
        for k in 0..2 {
            let d = a["value"][k].as_f64().unwrap() - b["value"][k].as_f64().unwrap();
            squared += d * d;
        }
    }
    let rmse = (squared / a.len() as f64).sqrt();
    assert!(rmse <= 1e-3, "position RMSE {rmse} m");

    for off in ["/v1/jobs?outliers=off", "/v1/jobs"] {
        let (status, off) = post_raw(&c, &s.url(off), corrupted.clone()).await;
        assert_eq!(status, 200, "{off}");
        assert!(off.get("outliers").is_none());
        assert!(off["summary"]["final_chi2"].as_f64().unwrap() > 100.0 * clean_chi2);
    }

    let (status, refused) = post_raw(&c, &s.url("/v1/jobs?outliers=sometimes"), clean).await;
    assert_eq!(status, 400, "{refused}");
    assert_eq!(refused["error"]["field"], "outliers", "{refused}");
}
