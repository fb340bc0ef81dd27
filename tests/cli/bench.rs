//! `hifar bench --quick --json`: real measurements of raw `mujoco.batch` stepping and the
//! native environment, reported in the documented JSON shape. Timings are never asserted.

use crate::common::{hifar, require_venv, stderr, stdout, tempdir};

#[test]
fn quick_bench_reports_raw_and_native_throughput_as_json() {
    require_venv();
    let dir = tempdir();
    let out = hifar(dir.path()).args(["bench", "--quick", "--json"]).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let doc: serde_json::Value = serde_json::from_str(stdout(&out).trim())
        .unwrap_or_else(|e| panic!("bench printed no JSON ({e}): {}", stdout(&out)));
    let results = doc["results"].as_array().expect("results list");
    for name in ["raw_batch", "native_env"] {
        let entry = results
            .iter()
            .find(|r| r["name"] == name)
            .unwrap_or_else(|| panic!("no {name} entry in {doc}"));
        assert_eq!(entry["batch"], 16, "{entry}");
        for key in ["physics_steps_per_s", "env_steps_per_s", "compile_s", "peak_rss_mb"] {
            assert!(entry[key].is_number(), "{name} lacks {key}: {entry}");
        }
        assert!(entry["physics_steps_per_s"].as_f64().unwrap() > 0.0, "{entry}");
    }
}
