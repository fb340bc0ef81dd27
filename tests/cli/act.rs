//! `hifar act`: input validation, and the expansion guarantee seen through the deployable
//! actor: the expanded stage-2 initial checkpoint gives the stage-1 actions for the old action
//! names whatever values the new observation features take.

use std::path::Path;

use serde_json::{json, Value};

use crate::common::{hifar, read_json, stderr, stdout, tempdir};
use crate::train::reference_run;

/// Deterministic pseudo-random values in [-1, 1) (a 64-bit LCG), so failures reproduce.
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

fn names(meta: &Value, key: &str) -> Vec<String> {
    meta[key].as_array().unwrap().iter().map(|v| v.as_str().unwrap().to_owned()).collect()
}

fn act(dir: &Path, checkpoint: &Path, obs: &[Vec<f64>]) -> Value {
    let input = dir.join(format!("in-{}.json", rand_suffix(obs)));
    std::fs::write(&input, json!({"obs": obs}).to_string()).unwrap();
    let out = hifar(dir).arg("act").arg(checkpoint).arg("--input").arg(&input).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    serde_json::from_str(stdout(&out).trim()).unwrap_or_else(|e| panic!("act printed no JSON ({e}): {}", stdout(&out)))
}

fn rand_suffix(obs: &[Vec<f64>]) -> String {
    format!("{:x}", obs.iter().flatten().fold(0u64, |h, v| h.rotate_left(7) ^ v.to_bits()))
}

#[test]
fn expanded_checkpoint_keeps_the_old_actions_whatever_the_new_features() {
    let run = &reference_run().run;
    let manifest = read_json(&run.join("manifest.json"));
    let stage1 = run.join(manifest["stages"][0]["final_checkpoint"].as_str().unwrap());
    let expanded = run.join(manifest["stages"][1]["init_checkpoint"].as_str().unwrap());
    let (meta1, meta2) = (read_json(&stage1.join("checkpoint.json")), read_json(&expanded.join("checkpoint.json")));
    let (obs1, obs2) = (names(&meta1, "obs_names"), names(&meta2, "obs_names"));
    let (act1, act2) = (names(&meta1, "action_names"), names(&meta2, "action_names"));
    assert!(obs2.len() > obs1.len(), "stage 2 should observe more features than stage 1");

    let dir = tempdir();
    let mut rng = Lcg(7);
    let rows1: Vec<Vec<f64>> = (0..4).map(|_| obs1.iter().map(|_| rng.next()).collect()).collect();
    let reference = act(dir.path(), &stage1, &rows1);
    assert_eq!(names(&reference, "action_names"), act1);

    for fill in 0..2 {
        // Same values for the old features (by name), fresh random values for the new ones.
        let rows2: Vec<Vec<f64>> = rows1
            .iter()
            .map(|row| {
                obs2.iter()
                    .map(|name| match obs1.iter().position(|n| n == name) {
                        Some(i) => row[i],
                        None => 3.0 * rng.next(),
                    })
                    .collect()
            })
            .collect();
        let expanded_out = act(dir.path(), &expanded, &rows2);
        assert_eq!(names(&expanded_out, "action_names"), act2);
        for (r, (a, b)) in reference["actions"]
            .as_array()
            .unwrap()
            .iter()
            .zip(expanded_out["actions"].as_array().unwrap())
            .enumerate()
        {
            for (j, name) in act1.iter().enumerate() {
                let k = act2.iter().position(|n| n == name).expect("old action kept");
                let (x, y) = (a[j].as_f64().unwrap(), b[k].as_f64().unwrap());
                assert!((x - y).abs() <= 1e-5 * (1.0 + x.abs()), "fill {fill}, row {r}, {name}: {x} vs {y}");
            }
        }
    }
}

#[test]
fn act_checks_row_width_against_the_checkpoint_before_starting_python() {
    let run = &reference_run().run;
    let manifest = read_json(&run.join("manifest.json"));
    let ckpt = run.join(manifest["stages"][0]["final_checkpoint"].as_str().unwrap());
    let n_obs = read_json(&ckpt.join("checkpoint.json"))["obs_names"].as_array().unwrap().len();
    let dir = tempdir();
    let input = dir.path().join("short.json");
    std::fs::write(&input, json!({"obs": [vec![0.0; n_obs], vec![0.0; n_obs - 1]]}).to_string()).unwrap();
    let out = hifar(dir.path()).arg("act").arg(&ckpt).arg("--input").arg(&input).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(err.contains("short.json") && err.contains("obs[1]") && err.contains(&n_obs.to_string()), "{err}");

    std::fs::write(&input, "{\"obs\": [[1.0,\n 2.0,]]}").unwrap();
    let out = hifar(dir.path()).arg("act").arg(&ckpt).arg("--input").arg(&input).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("short.json:2:"), "{}", stderr(&out));
}
