//! `hifar eval`: the plan's checks before Python starts, a quick evaluation of a run end to end,
//! and an interrupt that writes nothing.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use serde_json::Value;

use crate::common::{hifar, hifar_std, read_json, stderr, stdout, tempdir};
use crate::train::{copy_dir, reference_run};

/// A private copy of the reference run (evaluations write into `<run>/eval/`).
fn run_copy(dir: &Path) -> PathBuf {
    let run = dir.join("run");
    copy_dir(&reference_run().run, &run);
    run
}

/// The command log exists once Python has been started (its output is redirected there).
fn python_started(dir: &Path) -> bool {
    dir.join(".cache").join("hifar").join("hifar.log").exists()
}

fn final_checkpoint(run: &Path) -> PathBuf {
    let manifest = read_json(&run.join("manifest.json"));
    let last = manifest["stages"].as_array().unwrap().last().unwrap().clone();
    run.join(last["final_checkpoint"].as_str().unwrap())
}

#[test]
fn bad_arguments_are_refused_before_python_starts() {
    let dir = tempdir();
    let out = hifar(dir.path()).args(["eval", "nowhere", "--trials", "0"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("--trials 0"), "{}", stderr(&out));
    let out = hifar(dir.path()).args(["eval", "nowhere"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("nowhere: no such checkpoint or run directory"), "{}", stderr(&out));
    let out = hifar(dir.path()).args(["eval", "nowhere", "--protocol", "full"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("paper") && stderr(&out).contains("quick"), "{}", stderr(&out));
    let out = hifar(dir.path()).args(["eval", "nowhere", "--actor", "teacher"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("deployable") && stderr(&out).contains("privileged"), "{}", stderr(&out));
    assert!(!python_started(dir.path()));
}

#[test]
fn an_existing_output_directory_is_refused_without_force() {
    let dir = tempdir();
    let run = run_copy(dir.path());
    // The default output directory of a run names the protocol and the backend.
    let taken = run.join("eval").join("quick-mjx");
    std::fs::create_dir_all(&taken).unwrap();
    std::fs::write(taken.join("eval.json"), "{}").unwrap();
    let out = hifar(dir.path()).arg("eval").arg(&run).args(["--protocol", "quick", "--backend", "mjx"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("quick-mjx") && stderr(&out).contains("--force"), "{}", stderr(&out));
    // --out, for a checkpoint too.
    let checkpoint = final_checkpoint(&run);
    let out = hifar(dir.path()).arg("eval").arg(&checkpoint).arg("--out").arg(&taken).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(!python_started(dir.path()), "the refusal must come before Python starts");
    assert_eq!(std::fs::read_to_string(taken.join("eval.json")).unwrap(), "{}");
}

#[test]
fn a_run_whose_last_stage_is_unfinished_says_which_stage_it_stands_for() {
    let dir = tempdir();
    let run = run_copy(dir.path());
    // The run as `hifar train` leaves it while its last stage trains.
    let path = run.join("manifest.json");
    let completed = std::fs::read_to_string(&path).unwrap();
    let mut manifest = read_json(&path);
    let last = manifest["stages"].as_array_mut().unwrap().last_mut().unwrap();
    last["status"] = "running".into();
    last["final_checkpoint"] = Value::Null;
    let first = manifest["stages"][0]["name"].as_str().unwrap().to_owned();
    let last_name = manifest["stages"].as_array().unwrap().last().unwrap()["name"].as_str().unwrap().to_owned();
    std::fs::write(&path, serde_json::to_string_pretty(&manifest).unwrap()).unwrap();
    let taken = dir.path().join("taken");
    std::fs::create_dir_all(&taken).unwrap();
    // Refused for the existing --out (so Python never starts), after the note.
    let out = hifar(dir.path()).arg("eval").arg(&run).arg("--out").arg(&taken).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let note = format!("stage \"{last_name}\" is running; this is stage \"{first}\"'s final checkpoint");
    assert!(stderr(&out).contains(&note), "{}", stderr(&out));
    assert!(!python_started(dir.path()));
    // The same run completed says nothing of the kind.
    std::fs::write(&path, completed).unwrap();
    let out = hifar(dir.path()).arg("eval").arg(&run).arg("--out").arg(&taken).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(!stderr(&out).contains("note:"), "{}", stderr(&out));
}

#[test]
fn quick_evaluation_of_a_run_writes_and_prints_its_tables() {
    let dir = tempdir();
    let run = run_copy(dir.path());
    let args = ["--protocol", "quick", "--trials", "1", "--backend", "native", "--seed", "3"];
    let out = hifar(dir.path()).arg("eval").arg(&run).args(args).timeout(Duration::from_secs(900)).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let eval_dir = run.join("eval").join("quick-native");
    let doc = read_json(&eval_dir.join("eval.json"));
    assert_eq!(doc["protocol"], "quick");
    assert_eq!(doc["backend"], "native");
    assert_eq!(doc["seed"], 3);
    assert_eq!(doc["trials"], 1);
    assert_eq!(doc["stage"], "full");
    let checkpoint = final_checkpoint(&run);
    assert_eq!(doc["checkpoint"].as_str().map(PathBuf::from), Some(checkpoint.canonicalize().unwrap()));
    let cells = doc["cells"].as_array().unwrap();
    assert_eq!(cells.len(), 9);
    assert!(cells.iter().all(|c| c["trials"] == 1 && c["ci95"].as_array().map(Vec::len) == Some(2)));
    assert!(cells.iter().any(|c| c["experiment"] == "planar_push" && c["paper_success_rate"].is_number()));
    let markdown = std::fs::read_to_string(eval_dir.join("eval.md")).unwrap();
    assert!(stdout(&out).contains("## Standard supine and prone recovery"), "{}", stdout(&out));
    assert_eq!(stdout(&out).trim_end(), markdown.trim_end());
    let csv = std::fs::read_to_string(eval_dir.join("eval.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + cells.len());

    // Again: refused without --force, identical with it (same seed, same tables).
    let out = hifar(dir.path()).arg("eval").arg(&run).args(args).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    let out =
        hifar(dir.path()).arg("eval").arg(&run).args(args).arg("--force").timeout(Duration::from_secs(900)).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    let again: Value = read_json(&eval_dir.join("eval.json"));
    assert_eq!(again, doc);
}

#[test]
fn an_interrupted_evaluation_exits_130_and_writes_nothing() {
    let dir = tempdir();
    let run = run_copy(dir.path());
    let out_dir = dir.path().join("eval-out");
    let mut child = hifar_std(dir.path())
        .arg("eval")
        .arg(&run)
        .args(["--backend", "native", "--out"])
        .arg(&out_dir)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The paper protocol (54 cells × 100 trials, dozens of batches): an interrupt while the
    // rollout compiles or runs is answered at the next batch.
    let start = Instant::now();
    while !python_started(dir.path()) {
        if let Some(status) = child.try_wait().unwrap() {
            panic!("eval ended before the interrupt: {status}");
        }
        assert!(start.elapsed() < Duration::from_secs(300), "Python did not start within 5 minutes");
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_secs(3));
    let kill = std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.code(), Some(130), "{}", stderr(&out));
    assert!(stderr(&out).contains("interrupted; nothing written"), "{}", stderr(&out));
    assert!(!out_dir.exists());
    assert!(stdout(&out).is_empty());
}
