//! Curriculum errors, checkpoint expansion, and the refusal of checkpoints whose RMA adaptation
//! module never trained, through the real binary. A curriculum's syntax, types, names and
//! relations between stages are checked before the interpreter starts, what a stage means by
//! Python (`facade.check_stage`); such a checkpoint is refused before Python starts, and
//! expansion is pure Rust.

use std::path::{Path, PathBuf};

use hifar_cli::checkpoint::{self, Checkpoint, CheckpointMeta, Tensor};
use hifar_cli::curriculum;
use serde_json::json;

use crate::common::{data, hifar, require_venv, stderr, stdout, tempdir};

/// The fixtures of tests/data/bad, each with its expected `LINE:COL` and message fragment
/// (second line: `# expect: LINE:COL: fragment`).
fn bad_fixtures() -> Vec<(PathBuf, String, String)> {
    let dir = data("bad");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("tests/data/bad")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    files
        .into_iter()
        .map(|file| {
            let text = std::fs::read_to_string(&file).unwrap();
            let expect = text.lines().nth(1).and_then(|l| l.strip_prefix("# expect: ")).expect("an expect line").to_owned();
            let (position, fragment) = expect.split_once(": ").unwrap();
            (file, position.to_owned(), fragment.to_owned())
        })
        .collect()
}

#[test]
fn every_class_of_curriculum_error_exits_2_with_its_line() {
    require_venv();
    let dir = tempdir();
    let fixtures = bad_fixtures();
    assert!(fixtures.len() >= 20);
    let mut failures = Vec::new();
    for (file, position, fragment) in fixtures {
        let output = hifar(dir.path()).arg("check").arg(&file).output().unwrap();
        let err = stderr(&output);
        let first = err.lines().next().unwrap_or_default();
        let expected = format!("{}:{position}: ", file.display());
        if output.status.code() != Some(2) || !first.contains(&expected) || !first.contains(&fragment) {
            failures.push(format!(
                "{}: exit {:?}\n  expected …{expected}…{fragment}…\n  got      {first}",
                file.display(),
                output.status.code()
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// What a stage means is Python's to check; its messages reach the terminal at the line of the
/// key or value at fault, in file order, with exit code 2.
#[test]
fn stage_semantics_are_checked_by_python_at_their_lines() {
    require_venv();
    let dir = tempdir();
    let tiny = std::fs::read_to_string(data("tiny.toml")).unwrap();
    let line_col = |text: &str, needle: &str, offset: usize| -> String {
        let at = text.find(needle).unwrap_or_else(|| panic!("{needle}")) + offset;
        let line = text[..at].matches('\n').count() + 1;
        let col = at - text[..at].rfind('\n').map_or(0, |i| i + 1) + 1;
        format!("{line}:{col}")
    };
    let cases: &[(&str, &str, &str)] = &[
        ("discount = 0.97", "discount = 1.5", "discount = 1.5 is out of range; expected >= 0 and <= 1"),
        ("episode_s = 1.0", "episode_s = 0.01", "episode_s = 0.01 must be > ctrl_dt = 0.02"),
        ("policy_hidden = [16, 16]", "policy_hidden = [16, 0]", "policy_hidden[1] = 0; layer sizes must be positive"),
        ("slope_max_deg = 0.0", "slope_max_deg = 45.0", "slope_max_deg = 45 is out of range; expected >= 0 and <= 30"),
        ("settle_s = 0.2", "settle_s = 2.0", "settle_s = 2 must be < episode_s = 1"),
        ("settle_s = 0.2", "path_start_window_s = { kneel_path = 0.0 }\nsettle_s = 0.2", "kneel_path = 0 is out of range; expected > 0"),
        ("hold_s = 0.2", "hold_s = 1.0", "hold_s = 1 must be < episode_s = 1: no episode could ever count as standing"),
        ("interval_s = [2.0, 4.0]", "interval_s = [4.0, 2.0]", "interval_s = [4, 2]: min 4 > max 2"),
        ("hip_roll_ref = 0.0", "face_down_gate = [0.6, 0.3]\nhip_roll_ref = 0.0", "face_down_gate = [0.6, 0.3]: expected [full, zero] with -1 <= full < zero <= 1"),
        ("min_stand_rate = 0.8", "min_stand_rate = 1.2", "min_stand_rate = 1.2 is out of range; expected >= 0 and <= 1"),
        ("\"Left_Hip_Pitch\", \"Left_Knee_Pitch\"", "\"Left_Hip_Pitch\", \"Left_Hip_Pitch\"", "joint \"Left_Hip_Pitch\" is listed twice in controlled_joints"),
        ("range = [0.0, 0.05]", "range = [0.0, -0.05]", "dof_position.range = [0, -0.05]: gaussian ranges are [mean, std] and std -0.05 must be >= 0"),
        ("\"Right_Shoulder_Pitch\", \"Right_Elbow_Yaw\",\n", "\"Right_Shoulder_Pitch\",\n", "controlled_joints must be left/right symmetric for the mirror loss; missing Right_Elbow_Yaw (mirror of Left_Elbow_Yaw)"),
    ];
    let file = dir.path().join("c.toml");
    for (old, new, message) in cases {
        assert!(tiny.contains(old), "{old}");
        // Both stages' layers change alike (a stage that starts from the other keeps them).
        let text = if old.starts_with("policy_hidden") { tiny.replace(old, new) } else { tiny.replacen(old, new, 1) };
        std::fs::write(&file, &text).unwrap();
        let out = hifar(dir.path()).arg("check").arg(&file).output().unwrap();
        let err = stderr(&out);
        assert_eq!(out.status.code(), Some(2), "{new}: {err}");
        let first = err.lines().next().unwrap_or_default();
        assert!(first.contains(message), "{new}: expected …{message}…\n  got {first}");
        // A value at fault is pointed at (a bad list element: that element); a list that lacks
        // something, at its key.
        let expected = if message.contains("symmetric") {
            line_col(&text, "controlled_joints", 0)
        } else if message.starts_with("kneel_path") {
            line_col(&text, new, new.find("0.0").unwrap())
        } else if message.contains("listed twice") || message.contains("layer sizes") {
            line_col(&text, new, new.find(", ").unwrap() + 2)
        } else {
            line_col(&text, new, new.find('=').unwrap() + 2)
        };
        assert!(first.contains(&format!("{}:{expected}: ", file.display())), "{new}: expected at {expected}: {first}");
    }

    // Every problem, in file order, Python's and the values'.
    let text = tiny.replacen("learning_rate = 3e-4", "learning_rate = -1.0", 1).replacen("num_envs = 8", "num_envs = 0", 2);
    std::fs::write(&file, &text).unwrap();
    let out = hifar(dir.path()).arg("check").arg(&file).output().unwrap();
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "{err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.contains(&format!("{}:", file.display()))).collect();
    assert_eq!(lines.len(), 3, "{err}");
    assert!(lines[0].contains("num_envs = 0 is out of range; expected a positive integer"), "{err}");
    assert!(lines[1].contains("learning_rate = -1 is out of range; expected > 0"), "{err}");
    assert!(lines[2].contains("num_envs = 0"), "{err}");
}

#[test]
fn a_bad_curriculum_creates_no_run_directory() {
    let dir = tempdir();
    let run = dir.path().join("run");
    let output = hifar(dir.path())
        .args(["train", data("bad/unknown_joint.toml").to_str().unwrap(), "--run-dir"])
        .arg(&run)
        .output()
        .unwrap();
    assert_eq!(output.status.code(), Some(2), "{}", stderr(&output));
    assert!(stderr(&output).contains("unknown joint \"Left_Knee\""), "{}", stderr(&output));
    assert!(!run.exists());
}

#[test]
fn an_unreadable_curriculum_exits_2() {
    let dir = tempdir();
    let output = hifar(dir.path()).args(["check", "no/such/file.toml"]).output().unwrap();
    assert_eq!(output.status.code(), Some(2));
    assert!(stderr(&output).contains("no/such/file.toml: cannot read the curriculum"), "{}", stderr(&output));
}

/// A checkpoint of tiny.toml's "planar" stage laid out like the learner's (actor with an RMA
/// latent, critic with privileged inputs, normalizer, optimizer moment, step counter).
fn planar_checkpoint(dir: &Path) {
    let tiny = curriculum::load(&data("tiny.toml")).unwrap();
    let stage = &tiny.stages()[0];
    let f = curriculum::feature_names(stage);
    let (n_obs, n_priv, n_act) = (f.obs_names.len(), f.privileged_names.len(), f.action_names.len());
    let (hidden, latent) = (16, 4);
    let obs = json!({"features": "obs"});
    let act = json!({"features": "action"});
    let mut tensors = std::collections::BTreeMap::new();
    let mut annotations = serde_json::Map::new();
    let mut add = |name: &str, shape: Vec<usize>, axes: serde_json::Value, fill: serde_json::Value| {
        let n: usize = shape.iter().product();
        let values: Vec<f32> = (0..n).map(|i| ((i * 7919 % 113) as f32 - 56.0) / 50.0).collect();
        tensors.insert(name.to_owned(), Tensor::from_f32(shape.clone(), &values));
        annotations.insert(name.to_owned(), json!({"shape": shape, "axes": axes, "fill": fill}));
    };
    add("policy/hidden_0/kernel", vec![n_obs + latent, hidden], json!([[obs, {"fixed": latent}], null]), json!(0.0));
    add("policy/hidden_0/bias", vec![hidden], json!([null]), json!(null));
    add("policy/hidden_1/kernel", vec![hidden, hidden], json!([null, null]), json!(null));
    add("policy/hidden_1/bias", vec![hidden], json!([null]), json!(null));
    add("policy/hidden_2/kernel", vec![hidden, n_act], json!([null, [act]]), json!(0.0));
    add("policy/hidden_2/bias", vec![n_act], json!([[act]]), json!(0.0));
    add("policy/log_std", vec![n_act], json!([[act]]), json!("log_initial_action_std"));
    add("value/hidden_0/kernel", vec![n_obs + n_priv, hidden], json!([[obs, {"features": "privileged"}], null]), json!(0.0));
    add("normalizer/obs/mean", vec![n_obs], json!([[obs]]), json!(0.0));
    add("normalizer/obs/std", vec![n_obs], json!([[obs]]), json!(1.0));
    add("opt/policy/mu/hidden_0/kernel", vec![n_obs + latent, hidden], json!([[obs, {"fixed": latent}], null]), json!(0.0));
    tensors.insert("opt/count".into(), Tensor { dtype: safetensors::Dtype::I32, shape: vec![], data: 9i32.to_le_bytes().to_vec() });
    annotations.insert("opt/count".into(), json!({"shape": [], "axes": []}));
    let meta: CheckpointMeta = serde_json::from_value(json!({
        "format_version": 1, "stage": "planar", "env_steps": 192, "iteration": 3, "seed": 7, "prng_key": [0, 7],
        "obs_names": f.obs_names, "privileged_names": f.privileged_names, "action_names": f.action_names,
        "network": {"policy_hidden": [16, 16], "value_hidden": [16, 16], "activation": "elu",
                    "latent_dim": latent, "encoder_hidden": [16], "history_len": 4, "rma": true},
        "action": {"mapping": "current", "scale": 0.5, "clip": 1.0},
        "tensors": annotations,
    }))
    .unwrap();
    checkpoint::save(dir, &Checkpoint { dir: dir.to_path_buf(), meta, tensors, header: None }).unwrap();
}

#[test]
fn expand_checkpoint_adds_the_hip_roll_features() {
    let dir = tempdir();
    let src = dir.path().join("planar");
    planar_checkpoint(&src);
    let out = dir.path().join("full");
    let run = |out: &Path| {
        hifar(dir.path())
            .arg("expand-checkpoint")
            .arg(&src)
            .arg("--curriculum")
            .arg(data("tiny.toml"))
            .args(["--stage", "full", "--out"])
            .arg(out)
            .output()
            .unwrap()
    };
    let output = run(&out);
    assert!(output.status.success(), "{}", stderr(&output));
    let report = stdout(&output);
    assert!(report.contains("+2 actions (Left_Hip_Roll, Right_Hip_Roll)"), "{report}");
    assert!(report.contains("+6 obs (joint_pos/Left_Hip_Roll, joint_pos/Right_Hip_Roll, joint_vel/Left_Hip_Roll"), "{report}");

    let expanded = checkpoint::load(&out).unwrap();
    assert_eq!(expanded.meta.stage, "full");
    assert_eq!(expanded.meta.obs_names.len(), 42);
    assert_eq!(expanded.meta.action_names.len(), 12);
    assert_eq!(expanded.tensors["policy/hidden_0/kernel"].shape, vec![42 + 4, 16]);
    assert_eq!(expanded.tensors["policy/hidden_2/kernel"].shape, vec![16, 12]);
    // log_std of a new action: ln(initial_action_std) of stage "full" (0.5).
    let log_std = expanded.tensors["policy/log_std"].to_f32().unwrap();
    let hip = expanded.meta.action_names.iter().position(|a| a == "Left_Hip_Roll").unwrap();
    assert_eq!(log_std[hip], 0.5f32.ln());

    // Never overwrites; a bad checkpoint is a one-line runtime error (exit 1).
    let again = run(&out);
    assert_eq!(again.status.code(), Some(2), "{}", stderr(&again));
    std::fs::write(src.join("checkpoint.json"), "{ not json").unwrap();
    let corrupt = run(&dir.path().join("other"));
    assert_eq!(corrupt.status.code(), Some(1));
    let message = stderr(&corrupt);
    assert_eq!(message.lines().count(), 1, "{message}");
    assert!(message.contains("checkpoint.json:1:3: corrupt checkpoint metadata"), "{message}");
    let missing = hifar(dir.path())
        .args(["expand-checkpoint", "nowhere", "--curriculum"])
        .arg(data("tiny.toml"))
        .args(["--stage", "full", "--out", "x"])
        .output()
        .unwrap();
    assert_eq!(missing.status.code(), Some(1));
    assert!(stderr(&missing).contains("nowhere: no such checkpoint directory"), "{}", stderr(&missing));
}

/// Sets (or with `None` removes) the `"learner"` section of a checkpoint's `checkpoint.json`.
fn set_learner(checkpoint: &Path, learner: Option<serde_json::Value>) {
    let path = checkpoint.join("checkpoint.json");
    let mut meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    match learner {
        Some(learner) => meta["learner"] = learner,
        None => {
            meta.as_object_mut().unwrap().remove("learner");
        }
    }
    std::fs::write(&path, serde_json::to_string_pretty(&meta).unwrap()).unwrap();
}

/// `hifar act|eval|rollout|export TARGET` with arguments that are otherwise fine (`act` only
/// for a checkpoint: it takes no run directory).
fn deploy_commands(dir: &Path, target: &Path) -> Vec<(&'static str, std::process::Output)> {
    let input = dir.join("in.json");
    std::fs::write(&input, "{\"obs\": [[0.0]]}").unwrap();
    let run = |args: Vec<std::ffi::OsString>| hifar(dir).args(args).output().unwrap();
    let t = target.as_os_str().to_owned();
    let mut outputs = Vec::new();
    if target.join("checkpoint.json").is_file() {
        outputs.push(("act", run(vec!["act".into(), t.clone(), "--input".into(), input.into_os_string()])));
    }
    outputs.extend([
        ("eval", run(vec!["eval".into(), t.clone(), "--protocol".into(), "keystate".into(), "--backend".into(), "native".into()])),
        ("rollout", run(vec!["rollout".into(), t.clone(), "--scenario".into(), "stand".into(), "--out".into(), dir.join("e.mcap").into_os_string()])),
        ("export", run(vec!["export".into(), t, "--onnx".into(), dir.join("a.onnx").into_os_string()])),
    ]);
    outputs
}

#[test]
fn a_never_trained_adaptation_module_is_refused_before_python_starts() {
    let dir = tempdir();
    let run = dir.path().join("run");
    let planar = run.join("stages/planar/checkpoints/000000000192");
    std::fs::create_dir_all(planar.parent().unwrap()).unwrap();
    planar_checkpoint(&planar);
    let python_log = dir.path().join(".cache").join("hifar").join("hifar.log");
    let expect_refusal = |target: &Path, why: &str| {
        for (command, out) in deploy_commands(dir.path(), target) {
            let err = stderr(&out);
            assert_eq!(out.status.code(), Some(1), "{command}: {err}");
            assert_eq!(err.lines().count(), 1, "{command}: {err}");
            let expected = format!(
                "{}: its RMA adaptation module was never trained ({why}); train with rma.adaptation_env_steps > 0 or evaluate a later checkpoint",
                planar.display()
            );
            assert!(err.contains(&expected), "{command}:\n{err}\nexpected …{expected}");
        }
        assert!(!python_log.exists(), "the refusal must come before Python starts");
    };

    // A bare checkpoint without a learner section, then one whose stage never adapted.
    expect_refusal(&planar, "checkpoint.json has no \"learner\" section recording an adaptation phase");
    let learner = json!({"iteration": 3, "ppo_env_steps": 192, "adaptation_env_steps": 0, "phase": "done",
                         "finished_early": false, "num_envs": 8, "devices": 1, "ppo_budget": 192, "adaptation_budget": 0});
    set_learner(&planar, Some(learner.clone()));
    let why = "stage planar ended before its adaptation phase";
    expect_refusal(&planar, why);
    // `eval --actor privileged` acts without the adaptation module: no refusal, on to the next
    // check (an output directory that exists; its default name says the actor).
    let taken = planar.join("eval").join("keystate-native-privileged");
    std::fs::create_dir_all(&taken).unwrap();
    let out = hifar(dir.path())
        .arg("eval")
        .arg(&planar)
        .args(["--protocol", "keystate", "--backend", "native", "--actor", "privileged"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("keystate-native-privileged: the output directory exists"), "{}", stderr(&out));
    assert!(!python_log.exists());
    std::fs::remove_dir_all(planar.join("eval")).unwrap();

    // A run stands for the final checkpoint of its last completed stage: "planar" here, not
    // the later stage that was interrupted (whose stale final_checkpoint does not exist).
    let stage = |name: &str, status: &str, final_checkpoint: &str| {
        json!({"name": name, "seed": 1, "status": status, "init_from": null, "init_checkpoint": null,
               "final_checkpoint": final_checkpoint, "env_steps": 192, "best_stand_rate": null,
               "started_at": null, "ended_at": null})
    };
    let manifest = json!({
        "format_version": 1, "name": "run", "status": "interrupted",
        "curriculum": {"source": "tiny.toml", "copy": "curriculum.toml", "resolved": {"stage": [{"name": "planar"}, {"name": "full"}]}},
        "seed": 7, "backend": "native", "backend_reason": "test", "num_envs": null, "versions": {},
        "git_commit": null, "host": "test", "started_at": "2025-01-01T00:00:00Z", "ended_at": null, "sessions": [],
        "stages": [stage("planar", "completed", "stages/planar/checkpoints/000000000192"),
                   stage("full", "interrupted", "stages/full/checkpoints/000000000384")],
    });
    std::fs::write(run.join("manifest.json"), serde_json::to_string_pretty(&manifest).unwrap()).unwrap();
    expect_refusal(&run, why);

    // Once the adaptation phase has run, the refusal is gone (act then fails on its input).
    let mut adapted = learner;
    adapted["adaptation_env_steps"] = json!(64);
    set_learner(&planar, Some(adapted));
    let out = hifar(dir.path()).arg("act").arg(&planar).arg("--input").arg(dir.path().join("in.json")).output().unwrap();
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
    assert!(stderr(&out).contains("obs[0] has 1 values"), "{}", stderr(&out));
}
