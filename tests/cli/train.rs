//! `hifar train` end to end on the tiny curriculum (native backend, CPU), plus the run-directory
//! rules (no overwrite, the lock) and interrupt/resume.
//!
//! One uninterrupted reference run is trained once per test binary (`reference_run`) and
//! shared by the tests that only read it.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common::{data, hifar, hifar_std, read_json, require_venv, stderr, tempdir};

pub const TINY: &str = "tiny.toml";
const SEED: &str = "11";

/// A completed run of the tiny curriculum (trained on first use, kept for the whole binary).
/// It lives in cargo's per-target temporary directory, replaced by the next test session,
/// since a static's temporary directory would never be dropped.
pub struct Reference {
    pub run: PathBuf,
}

pub fn reference_run() -> &'static Reference {
    static REFERENCE: OnceLock<Reference> = OnceLock::new();
    REFERENCE.get_or_init(|| {
        require_venv();
        let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("hifar-reference");
        if dir.exists() {
            std::fs::remove_dir_all(&dir).unwrap();
        }
        std::fs::create_dir_all(&dir).unwrap();
        let run = dir.join("runs").join("reference");
        let out = hifar(&dir)
            .args(["train", data(TINY).to_str().unwrap(), "--backend", "native", "--seed", SEED, "--run-dir"])
            .arg(&run)
            .timeout(Duration::from_secs(1200))
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(0), "reference run failed:\n{}\nlog:\n{}", stderr(&out), log_tail(&run));
        Reference { run }
    })
}

fn log_tail(run: &Path) -> String {
    let text = std::fs::read_to_string(run.join("hifar.log")).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(40)..].join("\n")
}

pub fn stage_names(manifest: &Value) -> Vec<String> {
    manifest["stages"].as_array().unwrap().iter().map(|s| s["name"].as_str().unwrap().to_owned()).collect()
}

#[test]
fn tiny_curriculum_trains_both_stages_into_a_complete_run_directory() {
    let run = &reference_run().run;
    let manifest = read_json(&run.join("manifest.json"));
    assert_eq!(manifest["status"], "completed");
    assert_eq!(manifest["seed"], 11);
    assert_eq!(manifest["backend"], "native");
    assert!(manifest["versions"]["hifar"].is_string());
    assert!(manifest["versions"]["jax"].is_string(), "{}", manifest["versions"]);
    assert!(manifest["started_at"].is_string() && manifest["ended_at"].is_string());
    assert_eq!(manifest["sessions"].as_array().unwrap().len(), 1);
    assert!(manifest["curriculum"]["resolved"].is_object());
    assert!(run.join("curriculum.toml").is_file());
    assert!(run.join("hifar.log").is_file());
    assert!(run.join(".lock").is_file());

    let stages = manifest["stages"].as_array().unwrap();
    assert_eq!(stages.len(), 2, "tiny.toml has two stages");
    let mut seeds = Vec::new();
    for (i, stage) in stages.iter().enumerate() {
        let name = stage["name"].as_str().unwrap();
        // tiny.toml's second stage asks for a stand rate of 0.8 that three iterations cannot
        // reach, with on_miss = "continue": it is recorded as missed and the run completes.
        let expected = if i == 0 { "completed" } else { "threshold_missed" };
        assert_eq!(stage["status"], expected, "stage {name}");
        let ckpt = run.join(stage["final_checkpoint"].as_str().unwrap());
        assert!(ckpt.join("params.safetensors").is_file(), "{}", ckpt.display());
        let meta = read_json(&ckpt.join("checkpoint.json"));
        assert_eq!(meta["stage"], name);
        assert_eq!(meta["env_steps"], stage["env_steps"]);
        let latest = std::fs::read_to_string(run.join("stages").join(name).join("checkpoints").join("LATEST")).unwrap();
        assert!(ckpt.ends_with(latest.trim()) || Path::new(latest.trim()) == ckpt, "LATEST {latest} vs {}", ckpt.display());
        seeds.push(stage["seed"].as_u64().unwrap());
        if i == 1 {
            // Stage 2 starts from stage 1's final checkpoint expanded to its features.
            assert_eq!(stage["init_from"], stages[0]["name"]);
            let init = run.join(stage["init_checkpoint"].as_str().unwrap());
            let init_meta = read_json(&init.join("checkpoint.json"));
            let final_meta = read_json(&ckpt.join("checkpoint.json"));
            assert_eq!(init_meta["obs_names"], final_meta["obs_names"]);
            assert_eq!(init_meta["action_names"], final_meta["action_names"]);
        }
    }
    assert_ne!(seeds[0], seeds[1], "stage seeds differ");

    // metrics.jsonl: one object per iteration, both stages, increasing env steps per stage.
    let lines: Vec<Value> = std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).expect("every metrics line is JSON"))
        .collect();
    for name in stage_names(&manifest) {
        let mine: Vec<&Value> = lines.iter().filter(|l| l["stage"] == name.as_str()).collect();
        assert!(!mine.is_empty(), "no metrics for stage {name}");
        for pair in mine.windows(2) {
            let (a, b) = (&pair[0], &pair[1]);
            if a["phase"] == b["phase"] {
                assert!(b["env_steps"].as_u64() > a["env_steps"].as_u64(), "{a} then {b}");
            }
        }
        for line in &mine {
            for key in ["iteration", "env_steps", "wall_time", "steps_per_s", "phase", "losses", "rewards"] {
                assert!(line.get(key).is_some(), "metrics line lacks {key}: {line}");
            }
        }
    }

    // TensorBoard: one event directory per stage, readable by TensorBoard's record format.
    for name in stage_names(&manifest) {
        let dir = run.join("tensorboard").join(&name);
        let files: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
        assert_eq!(files.len(), 1, "{}", dir.display());
        let events = read_events_with_python(&files[0]);
        assert_eq!(events[0]["file_version"], "brain.Event:2");
        let tags: Vec<&str> = events[1..]
            .iter()
            .flat_map(|e| e["tags"].as_array().unwrap().iter().map(|t| t.as_str().unwrap()))
            .collect();
        assert!(tags.contains(&"steps_per_s"), "{tags:?}");
        assert!(tags.iter().any(|t| t.starts_with("losses/")), "{tags:?}");
    }
}

/// Reads an event file with the protobuf classes that ship with tensorboardX, checking both
/// masked CRCs of every record; returns [{"file_version", "step", "tags"}].
fn read_events_with_python(path: &Path) -> Vec<Value> {
    let script = r#"
import json, struct, sys
from tensorboardX.record_writer import masked_crc32c
from tensorboardX.proto import event_pb2
data = open(sys.argv[1], "rb").read()
out, at = [], 0
while at < len(data):
  header = data[at:at + 8]
  (n,) = struct.unpack("<Q", header)
  assert struct.unpack("<I", data[at + 8:at + 12])[0] == masked_crc32c(header)
  body = data[at + 12:at + 12 + n]
  assert struct.unpack("<I", data[at + 12 + n:at + 16 + n])[0] == masked_crc32c(body)
  event = event_pb2.Event.FromString(body)
  out.append({"file_version": event.file_version, "step": event.step, "wall_time": event.wall_time,
              "tags": [v.tag for v in event.summary.value]})
  at += 16 + n
print(json.dumps(out))
"#;
    let python = require_venv().join("bin").join("python");
    let out = std::process::Command::new(python).arg("-c").arg(script).arg(path).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    serde_json::from_slice(&out.stdout).unwrap()
}

#[test]
fn an_existing_run_directory_is_not_overwritten() {
    require_venv();
    let dir = tempdir();
    let run = dir.path().join("taken");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(run.join("precious.txt"), "keep me").unwrap();
    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--backend", "native", "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("already exists") && stderr(&out).contains("--resume"), "{}", stderr(&out));
    assert_eq!(std::fs::read_to_string(run.join("precious.txt")).unwrap(), "keep me");
    // --force does not delete a directory that is not a run directory either.
    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--backend", "native", "--force", "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(run.join("precious.txt").is_file());
}

#[test]
fn a_locked_run_directory_is_refused() {
    let reference = reference_run();
    let dir = tempdir();
    let run = dir.path().join("copy");
    copy_dir(&reference.run, &run);
    let lock = std::fs::OpenOptions::new().write(true).create(true).truncate(false).open(run.join(".lock")).unwrap();
    lock.try_lock().expect("the copy is not locked yet");
    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--resume", "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(stderr(&out).contains("in use by another hifar process"), "{}", stderr(&out));
    drop(lock);
    // Unlocked, resuming a finished run is a no-op that succeeds.
    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--resume", "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stderr(&out).contains("already finished"), "{}", stderr(&out));
}

#[test]
fn bad_num_envs_override_is_refused_before_a_run_directory_exists() {
    let dir = tempdir();
    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--num-envs", "0", "--run-dir", "r"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(!dir.path().join("r").exists());
}

#[test]
fn interrupted_run_resumes_to_the_same_parameters() {
    let reference = reference_run();
    let dir = tempdir();
    let run = dir.path().join("interrupted");
    let mut child = hifar_std(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--backend", "native", "--seed", SEED, "--run-dir"])
        .arg(&run)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Interrupt once the first stage has reported progress (its first iteration is done).
    let start = Instant::now();
    loop {
        let progressed = std::fs::read_to_string(run.join("metrics.jsonl")).is_ok_and(|t| t.lines().count() >= 1);
        if progressed {
            break;
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("training ended before the interrupt: {status}\n{}", log_tail(&run));
        }
        assert!(start.elapsed() < Duration::from_secs(900), "no progress within 15 minutes");
        std::thread::sleep(Duration::from_millis(50));
    }
    let kill = std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(130), "{}\n{}", stderr(&out), log_tail(&run));
    assert!(stderr(&out).contains("--resume"), "{}", stderr(&out));
    let manifest = read_json(&run.join("manifest.json"));
    assert_eq!(manifest["status"], "interrupted");
    assert!(
        manifest["stages"].as_array().unwrap().iter().any(|s| s["status"] == "interrupted")
            || manifest["stages"][0]["status"] == "completed",
        "{manifest}"
    );

    let out = hifar(dir.path())
        .args(["train", data(TINY).to_str().unwrap(), "--resume", "--run-dir"])
        .arg(&run)
        .timeout(Duration::from_secs(1200))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}\n{}", stderr(&out), log_tail(&run));
    let resumed = read_json(&run.join("manifest.json"));
    assert_eq!(resumed["status"], "completed");
    assert_eq!(resumed["sessions"].as_array().unwrap().len(), 2);
    let expected = read_json(&reference.run.join("manifest.json"));
    for (ours, theirs) in resumed["stages"].as_array().unwrap().iter().zip(expected["stages"].as_array().unwrap()) {
        assert_eq!(ours["env_steps"], theirs["env_steps"], "stage {}", ours["name"]);
        let a = run.join(ours["final_checkpoint"].as_str().unwrap()).join("params.safetensors");
        let b = reference.run.join(theirs["final_checkpoint"].as_str().unwrap()).join("params.safetensors");
        assert_same_tensors(&a, &b);
    }
    // The resumed metrics hold each iteration once.
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let reference_text = std::fs::read_to_string(reference.run.join("metrics.jsonl")).unwrap();
    assert_eq!(text.lines().count(), reference_text.lines().count());
}

fn assert_same_tensors(a: &Path, b: &Path) {
    let (bytes_a, bytes_b) = (std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    let (ta, tb) = (
        safetensors::SafeTensors::deserialize(&bytes_a).unwrap(),
        safetensors::SafeTensors::deserialize(&bytes_b).unwrap(),
    );
    let mut names_a = ta.names();
    let mut names_b = tb.names();
    names_a.sort();
    names_b.sort();
    assert_eq!(names_a, names_b, "{} vs {}", a.display(), b.display());
    for name in names_a {
        let (x, y) = (ta.tensor(name).unwrap(), tb.tensor(name).unwrap());
        assert_eq!(x.shape(), y.shape(), "{name}");
        assert!(x.data() == y.data(), "tensor {name} differs between {} and {}", a.display(), b.display());
    }
}

pub fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// tiny.toml with one setting of stage `full` changed (its torque limits).
fn tiny_with_other_full_stage(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(data(TINY)).unwrap();
    assert_eq!(text.matches("torque_limit_scale = 1.0").count(), 1, "tiny.toml's full stage sets 1.0");
    let path = dir.join("tiny_other_full.toml");
    std::fs::write(&path, text.replace("torque_limit_scale = 1.0", "torque_limit_scale = 0.9")).unwrap();
    path
}

#[test]
fn a_new_run_reuses_the_matching_leading_stages_of_another_run() {
    let reference = reference_run();
    let dir = tempdir();
    let run = dir.path().join("reusing");
    let curriculum = tiny_with_other_full_stage(dir.path());
    // Seed and backend come from the reused run.
    let out = hifar(dir.path())
        .args(["train", curriculum.to_str().unwrap(), "--reuse-stages-from"])
        .arg(&reference.run)
        .arg("--run-dir")
        .arg(&run)
        .timeout(Duration::from_secs(1200))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(0), "{}\n{}", stderr(&out), log_tail(&run));
    let manifest = read_json(&run.join("manifest.json"));
    let expected = read_json(&reference.run.join("manifest.json"));
    assert_eq!(manifest["status"], "completed");
    assert_eq!(manifest["seed"], expected["seed"]);
    let (planar, full) = (&manifest["stages"][0], &manifest["stages"][1]);
    let (reference_planar, reference_full) = (&expected["stages"][0], &expected["stages"][1]);
    // The planar stage is the reference's, copied: record, checkpoint, metrics lines, events.
    assert_eq!(planar["reused_from"], reference.run.to_str().unwrap());
    for key in ["status", "seed", "final_checkpoint", "env_steps", "started_at", "ended_at"] {
        assert_eq!(planar[key], reference_planar[key], "{key}");
    }
    let checkpoint = |run: &Path, stage: &Value, key: &str| run.join(stage[key].as_str().unwrap()).join("params.safetensors");
    assert_same_tensors(&checkpoint(&run, planar, "final_checkpoint"), &checkpoint(&reference.run, reference_planar, "final_checkpoint"));
    let planar_lines = |run: &Path| -> Vec<String> {
        let text = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
        text.lines().filter(|l| l.contains("\"stage\":\"planar\"")).map(str::to_owned).collect()
    };
    assert!(!planar_lines(&run).is_empty());
    assert_eq!(planar_lines(&run), planar_lines(&reference.run));
    assert!(run.join("tensorboard").join("planar").is_dir());
    // The full stage is trained anew, from the same expanded planar checkpoint.
    assert!(full.get("reused_from").is_none(), "{full}");
    assert_eq!(full["status"], reference_full["status"]);
    assert_same_tensors(&checkpoint(&run, full, "init_checkpoint"), &checkpoint(&reference.run, reference_full, "init_checkpoint"));
    assert!(run.join(full["final_checkpoint"].as_str().unwrap()).join("params.safetensors").is_file());
    assert!(std::fs::read_to_string(run.join("hifar.log")).unwrap().contains("stage planar: reused from"));
    let shown = hifar(dir.path()).args(["runs", "show"]).arg(&run).output().unwrap();
    assert!(crate::common::stdout(&shown).contains("reused        stage planar from"), "{}", crate::common::stdout(&shown));
}

#[test]
fn reuse_is_refused_before_a_run_directory_exists_when_nothing_or_everything_matches() {
    let reference = reference_run();
    let dir = tempdir();
    let run = dir.path().join("r");
    let refused = |curriculum: &Path, extra: &[&str]| {
        let out = hifar(dir.path())
            .args(["train", curriculum.to_str().unwrap(), "--reuse-stages-from"])
            .arg(&reference.run)
            .args(extra)
            .arg("--run-dir")
            .arg(&run)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
        assert!(!run.exists());
        stderr(&out)
    };
    // Another seed: no stage would train the same.
    let message = refused(&data(TINY), &["--seed", "12"]);
    assert!(message.contains("no stage of") && message.contains("seed 11") && message.contains("seed 12"), "{message}");
    // The same curriculum: every stage matches, there is nothing to train.
    let message = refused(&data(TINY), &[]);
    assert!(message.contains("nothing would be trained"), "{message}");
    // Another planar stage: its first stage differs.
    let text = std::fs::read_to_string(data(TINY)).unwrap().replacen("torque_limit_scale = 1.5", "torque_limit_scale = 1.4", 1);
    let other = dir.path().join("other_planar.toml");
    std::fs::write(&other, text).unwrap();
    let message = refused(&other, &[]);
    assert!(message.contains("stage 1 (planar) has other settings"), "{message}");
}
