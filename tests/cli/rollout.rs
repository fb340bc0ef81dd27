//! `hifar rollout`: argument checks before Python starts, and an MCAP recording of the reference
//! run read back with the Python `mcap` library (an independent reader): its channels, schemas,
//! encodings and message counts. Video and filmstrip are asked for only where offscreen OpenGL
//! works (probed with the test environment's Python).

use std::path::Path;
use std::process::Command;

use serde_json::Value;

use crate::common::{hifar, require_venv, stderr, stdout, tempdir};
use crate::train::reference_run;

/// tiny.toml's ctrl_dt is 0.02 s: 0.5 s is 25 control steps.
const DURATION: &str = "0.5";
const STEPS: u64 = 25;

fn refused(dir: &Path, args: &[&str], expected: &str) {
    let out = hifar(dir).arg("rollout").args(args).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{args:?}: {}", stderr(&out));
    let err = stderr(&out);
    assert!(err.contains(expected), "{args:?}: expected {expected:?} in {err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
}

#[test]
fn bad_arguments_are_refused_before_python_starts() {
    let dir = tempdir();
    let d = dir.path();
    std::fs::create_dir(d.join("ckpt")).unwrap();
    std::fs::write(d.join("taken.mcap"), b"keep").unwrap();
    refused(d, &["ckpt", "--scenario", "upright", "--out", "a.mcap"], "unknown scenario \"upright\"; valid: ksi_prone_1");
    refused(d, &["ckpt", "--terrain", "ice", "--out", "a.mcap"], "valid: flat, slope, obstacle");
    refused(d, &["ckpt", "--push-direction", "up", "--out", "a.mcap"], "valid: forward, backward, left, right");
    refused(d, &["ckpt", "--push-force=-5", "--out", "a.mcap"], "--push-force -5");
    refused(d, &["ckpt", "--duration", "0", "--out", "a.mcap"], "--duration 0");
    refused(d, &["ckpt", "--out", "missing/a.mcap"], "does not exist");
    refused(d, &["ckpt", "--out", "taken.mcap"], "already exists (pass --force");
    refused(d, &["ckpt", "--out", "a.mcap", "--video", "a.mcap"], "must differ");
    refused(d, &["ckpt", "--out", "a.mcap"], "neither a run directory");
    assert_eq!(std::fs::read(d.join("taken.mcap")).unwrap(), b"keep");
    assert!(!d.join("a.mcap").exists());
    assert!(!d.join(".cache/hifar/hifar.log").exists(), "Python never started (it logs there)");
}

/// Whether offscreen rendering works with the test environment's Python.
fn offscreen_gl(dir: &Path) -> bool {
    let python = require_venv().join("bin").join("python");
    let out = Command::new(python)
        .current_dir(dir)
        .args(["-c", "from jax_env.evaluation import recording; print(recording.offscreen_gl() or '')"])
        .output()
        .unwrap();
    out.status.success() && !String::from_utf8_lossy(&out.stdout).trim().is_empty()
}

/// Channels of an MCAP file as read by the Python mcap library:
/// {topic: {"schema", "schema_encoding", "message_encoding", "count", "first": message}}.
fn read_back(path: &Path) -> Value {
    let python = require_venv().join("bin").join("python");
    let script = r#"
import json, sys
from mcap.reader import make_reader
with open(sys.argv[1], "rb") as f:
  reader = make_reader(f)
  out = {}
  for schema, channel, message in reader.iter_messages(log_time_order=True):
    entry = out.setdefault(channel.topic, {
        "schema": schema.name, "schema_encoding": schema.encoding,
        "message_encoding": channel.message_encoding, "count": 0, "times": [],
        "schema_title": json.loads(schema.data).get("title"),
        "first": json.loads(message.data)})
    entry["count"] += 1
    entry["times"].append(message.log_time)
  print(json.dumps(out))
"#;
    let out = Command::new(python).args(["-c", script]).arg(path).output().unwrap();
    assert!(out.status.success(), "mcap reader failed: {}", stderr(&out));
    serde_json::from_str(&stdout(&out)).unwrap()
}

#[test]
fn a_recording_of_the_reference_run_reads_back_with_the_expected_channels() {
    let run = &reference_run().run;
    let dir = tempdir();
    let d = dir.path();
    let pictures = offscreen_gl(d);
    let mut cmd = hifar(d);
    cmd.args(["rollout"]).arg(run).args(["--scenario", "prone", "--push-force", "50", "--backend", "native"]);
    cmd.args(["--duration", DURATION, "--seed", "2", "--out", "episode.mcap"]);
    if pictures {
        cmd.args(["--video", "episode.mp4", "--filmstrip", "episode.png"]);
    }
    let out = cmd.output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let summary = stderr(&out);
    assert!(summary.contains(&format!("{STEPS} steps")) && summary.contains("episode.mcap"), "{summary}");
    let printed: Vec<String> = stdout(&out).lines().map(str::to_owned).collect();
    assert_eq!(printed.len(), if pictures { 3 } else { 1 }, "{printed:?}");
    assert!(printed[0].ends_with("episode.mcap"));

    let channels = read_back(&d.join("episode.mcap"));
    let expected = [
        ("/tf", "foxglove.FrameTransforms", STEPS),
        ("/scene", "foxglove.SceneUpdate", 1),
        ("/joint_states", "hifar.JointStates", STEPS),
        ("/torso_pitch", "hifar.TorsoPitch", STEPS),
        ("/rewards", "hifar.Rewards", STEPS),
        ("/standing", "hifar.Standing", STEPS),
        ("/push", "hifar.Push", STEPS),
    ];
    assert_eq!(channels.as_object().unwrap().len(), expected.len(), "{channels}");
    for (topic, schema, count) in expected {
        let c = &channels[topic];
        assert_eq!(c["schema"], schema, "{topic}");
        assert_eq!(c["schema_title"], schema, "{topic}");
        assert_eq!(c["schema_encoding"], "jsonschema", "{topic}");
        assert_eq!(c["message_encoding"], "json", "{topic}");
        assert_eq!(c["count"], count, "{topic}");
    }
    // Log times are the simulated time: 0, 20 ms, ..., one per control step.
    let times: Vec<u64> = channels["/tf"]["times"].as_array().unwrap().iter().map(|t| t.as_u64().unwrap()).collect();
    assert_eq!(times, (0..STEPS).map(|i| i * 20_000_000).collect::<Vec<_>>());

    let tf = &channels["/tf"]["first"]["transforms"];
    assert_eq!(tf.as_array().unwrap().len(), 24, "world → every robot body");
    assert_eq!(tf[0]["parent_frame_id"], "world");
    assert_eq!(tf[0]["child_frame_id"], "Trunk");
    assert_eq!(tf[0]["timestamp"], serde_json::json!({"sec": 0, "nsec": 0}));
    let q = &tf[0]["rotation"];
    let norm: f64 = ["x", "y", "z", "w"].iter().map(|k| q[k].as_f64().unwrap().powi(2)).sum();
    assert!((norm - 1.0).abs() < 1e-9, "{q}");
    let entities = channels["/scene"]["first"]["entities"].as_array().unwrap();
    assert_eq!(entities.len(), 25, "24 bodies and the world");
    assert!(entities.iter().all(|e| e["frame_locked"] == true && e["frame_id"] == e["id"]));
    let world = entities.iter().find(|e| e["id"] == "world").unwrap();
    assert_eq!(world["cubes"].as_array().unwrap().len(), 1, "the floor");
    let joints = &channels["/joint_states"]["first"];
    assert_eq!(joints["name"].as_array().unwrap().len(), 23);
    assert_eq!(joints["effort"].as_array().unwrap().len(), 23);
    assert!(channels["/rewards"]["first"]["terms"]["standing"].is_number());
    assert_eq!(channels["/standing"]["first"]["standing"], false);

    if pictures {
        assert!(std::fs::metadata(d.join("episode.mp4")).unwrap().len() > 0);
        assert!(std::fs::metadata(d.join("episode.png")).unwrap().len() > 0);
    }
    // No temporary files are left beside the outputs.
    let leftovers: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.') && n != ".cache")
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    // The same output again is refused without --force.
    let again = hifar(d).args(["rollout"]).arg(run).args(["--out", "episode.mcap"]).output().unwrap();
    assert_eq!(again.status.code(), Some(2), "{}", stderr(&again));
}
