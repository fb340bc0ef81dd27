//! `hifar export`: the real binary exports the reference run's final checkpoint, and
//! onnxruntime (run by the test environment's Python) on the written file gives the actions
//! `hifar act` prints; refusals of an existing output, a missing directory and bad targets
//! exit 2 before Python starts.

use std::path::Path;

use serde_json::{json, Value};

use crate::common::{hifar, read_json, stderr, stdout, tempdir, venv};
use crate::train::reference_run;

/// Runs `model.onnx` with onnxruntime on `input.json` ({"obs", "history"}) and prints
/// {"action", "joint_target", "metadata"} as JSON.
const ONNX_RUNNER: &str = r#"
import json, sys
import numpy as np, onnx, onnxruntime as ort
model, data = sys.argv[1], json.load(open(sys.argv[2]))
session = ort.InferenceSession(model, providers=["CPUExecutionProvider"])
feed = {"obs": np.asarray(data["obs"], np.float32), "history": np.asarray(data["history"], np.float32)}
action, target = session.run(["action", "joint_target"], feed)
props = {p.key: p.value for p in onnx.load(model).metadata_props}
print(json.dumps({"action": action.tolist(), "joint_target": target.tolist(), "metadata": props}))
"#;

fn run_onnx(dir: &Path, model: &Path, input: &Path) -> Value {
    let out = std::process::Command::new(venv().join("bin").join("python"))
        .current_dir(dir)
        .arg("-c")
        .arg(ONNX_RUNNER)
        .arg(model)
        .arg(input)
        .output()
        .unwrap();
    assert!(out.status.success(), "onnxruntime runner failed: {}", stderr(&out));
    serde_json::from_str(stdout(&out).trim()).unwrap()
}

/// Deterministic pseudo-random values in [-1, 1).
fn values(seed: &mut u64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|_| {
            *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((*seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
        .collect()
}

#[test]
fn exported_onnx_gives_the_actions_hifar_act_prints() {
    let run = &reference_run().run;
    let manifest = read_json(&run.join("manifest.json"));
    let stages = manifest["stages"].as_array().unwrap();
    let last = stages.last().unwrap();
    let checkpoint = run.join(last["final_checkpoint"].as_str().unwrap());
    let meta = read_json(&checkpoint.join("checkpoint.json"));
    let n_obs = meta["obs_names"].as_array().unwrap().len();
    let n_act = meta["action_names"].as_array().unwrap().len();
    let h = meta["network"]["history_len"].as_u64().unwrap() as usize;

    let dir = tempdir();
    let model = dir.path().join("actor.onnx");
    // The run directory stands for its last stage's final checkpoint.
    let out = hifar(dir.path()).arg("export").arg(run).arg("--onnx").arg("actor.onnx").output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let printed = stdout(&out);
    assert!(printed.contains(&format!("wrote {}", model.display())), "{printed}");
    assert!(printed.contains(&format!("obs [N, {n_obs}], history [N, {h}, {n_obs}]")), "{printed}");
    assert!(printed.contains(&format!("action [N, {n_act}], joint_target [N, {n_act}]")), "{printed}");
    assert!(printed.contains("max |onnx - jax|"), "{printed}");
    assert!(model.is_file());
    let leftovers: Vec<_> = std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name()).filter(|n| n.to_string_lossy().contains(".tmp")).collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");

    // Two rows with a nonzero history, through onnxruntime and through `hifar act`.
    let mut seed = 5;
    let obs: Vec<Vec<f64>> = (0..2).map(|_| values(&mut seed, n_obs)).collect();
    let history: Vec<Vec<Vec<f64>>> = (0..2).map(|_| (0..h).map(|_| values(&mut seed, n_obs)).collect()).collect();
    let input = dir.path().join("input.json");
    std::fs::write(&input, json!({"obs": obs, "history": history}).to_string()).unwrap();
    let onnx = run_onnx(dir.path(), &model, &input);
    let act = hifar(dir.path()).arg("act").arg(&checkpoint).arg("--input").arg(&input).output().unwrap();
    assert_eq!(act.status.code(), Some(0), "{}", stderr(&act));
    let act: Value = serde_json::from_str(stdout(&act).trim()).unwrap();
    for (r, (a, b)) in onnx["action"].as_array().unwrap().iter().zip(act["actions"].as_array().unwrap()).enumerate() {
        for j in 0..n_act {
            let (x, y) = (a[j].as_f64().unwrap(), b[j].as_f64().unwrap());
            assert!((x - y).abs() <= 1e-5, "row {r}, action {j}: onnx {x} vs act {y}");
        }
    }

    // The metadata documents the interface and where the file came from.
    let props = &onnx["metadata"];
    let parse = |key: &str| -> Value { serde_json::from_str(props[key].as_str().unwrap_or_else(|| panic!("no {key}"))).unwrap() };
    assert_eq!(parse("obs_names"), meta["obs_names"]);
    assert_eq!(parse("action_names"), meta["action_names"]);
    assert_eq!(parse("history_len"), meta["network"]["history_len"]);
    assert_eq!(props["mapping"], meta["action"]["mapping"]);
    assert_eq!(parse("scale"), meta["action"]["scale"]);
    // The run's curriculum gives the stage's control period.
    let stage = manifest["curriculum"]["resolved"]["stage"].as_array().unwrap().iter().find(|s| s["name"] == last["name"]).unwrap();
    assert_eq!(parse("ctrl_dt"), stage["sim"]["ctrl_dt"]);
    assert_eq!(Path::new(props["checkpoint"].as_str().unwrap()), std::fs::canonicalize(&checkpoint).unwrap());
    assert_eq!(parse("checkpoint_env_steps"), meta["env_steps"]);
}

#[test]
fn export_refuses_an_existing_output_and_a_missing_directory() {
    let run = &reference_run().run;
    let dir = tempdir();
    let existing = dir.path().join("actor.onnx");
    std::fs::write(&existing, "keep me").unwrap();
    let out = hifar(dir.path()).arg("export").arg(run).arg("--onnx").arg(&existing).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("already exists (pass --force to replace it)"), "{}", stderr(&out));
    assert_eq!(std::fs::read_to_string(&existing).unwrap(), "keep me");

    let out = hifar(dir.path()).arg("export").arg(run).arg("--onnx").arg("missing/actor.onnx").output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("does not exist (create it first)"), "{}", stderr(&out));

    let out = hifar(dir.path()).arg("export").arg(run).arg("--onnx").arg(dir.path()).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("is a directory"), "{}", stderr(&out));
}

#[test]
fn export_names_a_bad_target() {
    let dir = tempdir();
    let out = hifar(dir.path()).args(["export", "no-such-run", "--onnx", "a.onnx"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("no-such-run: no such checkpoint or run directory"), "{}", stderr(&out));

    std::fs::create_dir(dir.path().join("plain")).unwrap();
    let out = hifar(dir.path()).args(["export", "plain", "--onnx", "a.onnx"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("plain: neither a run directory (manifest.json) nor a checkpoint directory (checkpoint.json)"), "{}", stderr(&out));
    assert!(!dir.path().join("a.onnx").exists());
}
