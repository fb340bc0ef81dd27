//! Bad usage and bad input files: exit 2 with a message that names the problem.

use crate::common::{hifar, hifar_std, read_json, repo_root, require_venv, stderr, tempdir};

#[test]
fn no_command_is_a_usage_error() {
    let dir = tempdir();
    let out = hifar(dir.path()).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("Usage"), "{}", stderr(&out));
}

#[test]
fn unknown_command_and_flag_are_usage_errors() {
    let dir = tempdir();
    for args in [&["fly"][..], &["train", "x.toml", "--turbo"], &["train", "x.toml", "--backend", "gpu"]] {
        let out = hifar(dir.path()).args(args).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}: {}", stderr(&out));
    }
}

#[test]
fn resume_needs_a_run_dir_and_excludes_force() {
    let dir = tempdir();
    let out = hifar(dir.path()).args(["train", "x.toml", "--resume"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("--run-dir"), "{}", stderr(&out));
    let out = hifar(dir.path()).args(["train", "x.toml", "--run-dir", "r", "--resume", "--force"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(stderr(&out).contains("--force"), "{}", stderr(&out));
}

#[test]
fn missing_curriculum_names_the_file() {
    let dir = tempdir();
    for command in ["check", "train"] {
        let out = hifar(dir.path()).args([command, "nope.toml"]).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{command}: {}", stderr(&out));
        assert!(stderr(&out).contains("nope.toml"), "{command}: {}", stderr(&out));
        assert!(!dir.path().join("runs").exists(), "{command} created a run directory");
    }
}

#[test]
fn runs_lists_nothing_and_show_rejects_unknown_runs() {
    let dir = tempdir();
    let out = hifar(dir.path()).args(["runs"]).output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("no runs"));
    let out = hifar(dir.path()).args(["runs", "show", "ghost"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("ghost"), "{}", stderr(&out));
}

#[test]
fn act_refuses_a_missing_checkpoint_with_exit_1() {
    let dir = tempdir();
    std::fs::write(dir.path().join("in.json"), r#"{"obs": [[0.0]]}"#).unwrap();
    let out = hifar(dir.path()).args(["act", "no-such-checkpoint", "--input", "in.json"]).output().unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(stderr(&out).contains("no-such-checkpoint"), "{}", stderr(&out));
    assert_eq!(stderr(&out).lines().count(), 1, "{}", stderr(&out));
}

#[test]
fn doctor_without_a_venv_says_to_run_setup() {
    let dir = tempdir();
    let out = hifar(dir.path()).env("HIFAR_VENV", dir.path().join("none")).arg("doctor").output().unwrap();
    assert_eq!(out.status.code(), Some(1), "{}", stderr(&out));
    assert!(String::from_utf8_lossy(&out.stdout).contains("run `hifar setup`"));
    assert!(!dir.path().join("none").exists(), "doctor must not create the venv");
}

#[test]
fn setup_is_a_no_op_when_the_venv_is_current() {
    // Only meaningful for a venv made by `hifar setup` (tests/run.sh makes one).
    let venv = crate::common::venv();
    if !venv.join("hifar-setup.json").is_file() {
        eprintln!("skipped: {} was not created by `hifar setup`", venv.display());
        return;
    }
    let dir = tempdir();
    let before = read_json(&venv.join("hifar-setup.json"));
    let out = hifar(dir.path()).arg("setup").output().unwrap();
    assert_eq!(out.status.code(), Some(0), "{}", stderr(&out));
    assert!(stderr(&out).contains("up to date"), "{}", stderr(&out));
    assert_eq!(read_json(&venv.join("hifar-setup.json")), before);
}

#[test]
fn a_closed_stdout_ends_the_command_quietly() {
    // `hifar check FILE | head -0`: the reader is gone before hifar prints (Python starts first).
    require_venv();
    let dir = tempdir();
    let quickstart = repo_root().join("curricula").join("quickstart.toml");
    let mut child = hifar_std(dir.path())
        .args(["check", quickstart.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    use std::os::unix::process::ExitStatusExt;
    assert!(out.status.success() || out.status.signal() == Some(libc::SIGPIPE), "{:?}: {err}", out.status);
}
