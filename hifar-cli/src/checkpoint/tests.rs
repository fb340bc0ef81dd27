//! Expansion on synthetic checkpoints laid out like the learner's: an actor MLP reading
//! normalized observations plus an RMA latent, a critic reading observations and privileged
//! features, an adaptation module reading a history of observations, optimizer moments, and
//! integer / scalar bookkeeping tensors.

use std::path::{Path, PathBuf};

use serde_json::json;

use super::*;

const HIDDEN: usize = 5;
const LATENT: usize = 2;
const HISTORY: usize = 3;

fn names(list: &[&str]) -> Vec<String> {
    list.iter().map(|s| s.to_string()).collect()
}

fn old_features() -> FeatureNames {
    FeatureNames { obs_names: names(&["g", "a", "c"]), privileged_names: names(&["p"]), action_names: names(&["A", "C"]) }
}

/// New features inserted between old ones, so old entries must move.
fn new_features() -> FeatureNames {
    FeatureNames {
        obs_names: names(&["g", "a", "b", "c", "d"]),
        privileged_names: names(&["p"]),
        action_names: names(&["A", "B", "C"]),
    }
}

/// Deterministic pseudo-random values in [-1, 1).
fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (0..n)
        .map(|_| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((state >> 33) as f64 / (1u64 << 31) as f64 * 2.0 - 1.0) as f32
        })
        .collect()
}

fn annotation(shape: Vec<usize>, axes: serde_json::Value, fill: serde_json::Value) -> TensorMeta {
    serde_json::from_value(json!({"shape": shape, "axes": axes, "fill": fill})).unwrap()
}

fn synthetic(dir: &Path) -> Checkpoint {
    let f = old_features();
    let (n_obs, n_priv, n_act) = (f.obs_names.len(), f.privileged_names.len(), f.action_names.len());
    let obs = json!({"features": "obs"});
    let mut tensors = BTreeMap::new();
    let mut annotations = BTreeMap::new();
    let mut add = |name: &str, tensor: Tensor, meta: TensorMeta| {
        assert_eq!(tensor.shape, meta.shape, "{name}");
        tensors.insert(name.to_owned(), tensor);
        annotations.insert(name.to_owned(), meta);
    };
    let in_actor = n_obs + LATENT;
    let kernel_axes = json!([[obs, {"fixed": LATENT}], null]);
    add(
        "policy/hidden_0/kernel",
        Tensor::from_f32(vec![in_actor, HIDDEN], &values(in_actor * HIDDEN, 1)),
        annotation(vec![in_actor, HIDDEN], kernel_axes.clone(), json!(0.0)),
    );
    add("policy/hidden_0/bias", Tensor::from_f32(vec![HIDDEN], &values(HIDDEN, 2)), annotation(vec![HIDDEN], json!([null]), json!(null)));
    add(
        "policy/hidden_1/kernel",
        Tensor::from_f32(vec![HIDDEN, n_act], &values(HIDDEN * n_act, 3)),
        annotation(vec![HIDDEN, n_act], json!([null, [{"features": "action"}]]), json!(0.0)),
    );
    add(
        "policy/hidden_1/bias",
        Tensor::from_f32(vec![n_act], &values(n_act, 4)),
        annotation(vec![n_act], json!([[{"features": "action"}]]), json!(0.0)),
    );
    add(
        "policy/log_std",
        Tensor::from_f32(vec![n_act], &[-0.3, -0.7]),
        annotation(vec![n_act], json!([[{"features": "action"}]]), json!("log_initial_action_std")),
    );
    let in_value = n_obs + n_priv;
    add(
        "value/hidden_0/kernel",
        Tensor::from_f32(vec![in_value, HIDDEN], &values(in_value * HIDDEN, 5)),
        annotation(vec![in_value, HIDDEN], json!([[obs, {"features": "privileged"}], null]), json!(0.0)),
    );
    let in_adapt = HISTORY * n_obs;
    add(
        "adaptation/hidden_0/kernel",
        Tensor::from_f32(vec![in_adapt, HIDDEN], &values(in_adapt * HIDDEN, 6)),
        annotation(vec![in_adapt, HIDDEN], json!([[obs, obs, obs], null]), json!(0.0)),
    );
    add(
        "normalizer/obs/mean",
        Tensor::from_f32(vec![n_obs], &[0.1, 0.2, 0.3]),
        annotation(vec![n_obs], json!([[obs]]), json!(0.0)),
    );
    add("normalizer/obs/std", Tensor::from_f32(vec![n_obs], &[2.0, 3.0, 4.0]), annotation(vec![n_obs], json!([[obs]]), json!(1.0)));
    add("normalizer/count", Tensor::from_f32(vec![], &[1234.0]), annotation(vec![], json!([]), json!(null)));
    add(
        "opt/policy/mu/hidden_0/kernel",
        Tensor::from_f32(vec![in_actor, HIDDEN], &values(in_actor * HIDDEN, 7)),
        annotation(vec![in_actor, HIDDEN], kernel_axes, json!(0.0)),
    );
    add(
        "opt/count",
        Tensor { dtype: Dtype::I32, shape: vec![], data: 77i32.to_le_bytes().to_vec() },
        annotation(vec![], json!([]), json!(null)),
    );
    let meta: CheckpointMeta = serde_json::from_value(json!({
        "format_version": 1, "stage": "planar", "env_steps": 4096, "iteration": 8, "seed": 7,
        "prng_key": [0, 123],
        "obs_names": f.obs_names, "privileged_names": f.privileged_names, "action_names": f.action_names,
        "network": {"policy_hidden": [HIDDEN], "value_hidden": [HIDDEN], "activation": "elu",
                    "latent_dim": LATENT, "encoder_hidden": [HIDDEN], "history_len": HISTORY, "rma": true},
        "action": {"mapping": "current", "scale": 0.5, "clip": 1.0},
        "tensors": {},
        "learner_note": "kept as is",
    }))
    .unwrap();
    let mut checkpoint = Checkpoint { dir: dir.to_path_buf(), meta, tensors, header: None };
    checkpoint.meta.tensors = annotations;
    checkpoint.meta.check().unwrap();
    checkpoint
}

/// Writes the synthetic checkpoint (plus a rollout state) under `root/src`.
fn write_synthetic(root: &Path) -> PathBuf {
    let dir = root.join("src");
    save(&dir, &synthetic(&dir)).unwrap();
    std::fs::write(dir.join(ROLLOUT_FILE), b"rollout").unwrap();
    dir
}

fn f32s(checkpoint: &Checkpoint, name: &str) -> Vec<f32> {
    checkpoint.tensors[name].to_f32().unwrap()
}

/// The deterministic actor: normalized obs ++ latent -> elu(hidden) -> mean actions.
fn actor(checkpoint: &Checkpoint, obs: &[f32], latent: &[f32]) -> Vec<f32> {
    let mean = f32s(checkpoint, "normalizer/obs/mean");
    let std = f32s(checkpoint, "normalizer/obs/std");
    let mut x: Vec<f32> = obs.iter().zip(&mean).zip(&std).map(|((o, m), s)| (o - m) / s).collect();
    x.extend_from_slice(latent);
    let dense = |x: &[f32], kernel: &str, bias: &str| -> Vec<f32> {
        let k = f32s(checkpoint, kernel);
        let b = f32s(checkpoint, bias);
        let cols = b.len();
        (0..cols).map(|j| b[j] + x.iter().enumerate().map(|(i, xi)| xi * k[i * cols + j]).sum::<f32>()).collect()
    };
    let h: Vec<f32> =
        dense(&x, "policy/hidden_0/kernel", "policy/hidden_0/bias").into_iter().map(|v| if v > 0.0 { v } else { v.exp() - 1.0 }).collect();
    dense(&h, "policy/hidden_1/kernel", "policy/hidden_1/bias")
}

#[test]
fn expansion_moves_old_entries_and_fills_new_ones() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let out = root.path().join("expanded");
    let report = expand(&src, &new_features(), "full", 0.5f64.ln(), &out).unwrap();
    assert_eq!(report.added_obs, names(&["b", "d"]));
    assert!(report.added_privileged.is_empty());
    assert_eq!(report.added_actions, names(&["B"]));
    assert_eq!(report.unchanged, 3, "bias, normalizer/count and opt/count do not change");
    assert_eq!(report.resized.len(), 9);
    assert!(report.to_string().starts_with("expanded stage planar into stage full: +2 obs (b, d); +0 privileged; +1 actions (B);"));

    let old = load(&src).unwrap();
    let new = load(&out).unwrap();
    assert_eq!(new.meta.stage, "full");
    assert_eq!(new.meta.feature_names(), new_features());
    assert_eq!(new.meta.env_steps, 4096);
    assert_eq!(new.meta.extra["learner_note"], json!("kept as is"));
    assert!(!out.join(ROLLOUT_FILE).exists(), "a new stage starts fresh rollouts");

    // First layer: old obs rows moved to their new positions (c: 2 -> 3), new rows zero,
    // latent rows shifted behind the new obs.
    let (k_old, k_new) = (f32s(&old, "policy/hidden_0/kernel"), f32s(&new, "policy/hidden_0/kernel"));
    assert_eq!(new.tensors["policy/hidden_0/kernel"].shape, vec![5 + LATENT, HIDDEN]);
    assert_eq!(new.meta.tensors["policy/hidden_0/kernel"].shape, vec![5 + LATENT, HIDDEN]);
    let row = |k: &[f32], r: usize| k[r * HIDDEN..(r + 1) * HIDDEN].to_vec();
    for (old_row, new_row) in [(0, 0), (1, 1), (2, 3), (3, 5), (4, 6)] {
        assert_eq!(row(&k_old, old_row), row(&k_new, new_row), "row {old_row} -> {new_row}");
    }
    for new_row in [2, 4] {
        assert_eq!(row(&k_new, new_row), vec![0.0; HIDDEN]);
    }
    // Output layer: a new zero column for B between A and C.
    let (o_old, o_new) = (f32s(&old, "policy/hidden_1/kernel"), f32s(&new, "policy/hidden_1/kernel"));
    for r in 0..HIDDEN {
        assert_eq!([o_new[r * 3], o_new[r * 3 + 1], o_new[r * 3 + 2]], [o_old[r * 2], 0.0, o_old[r * 2 + 1]]);
    }
    assert_eq!(f32s(&new, "policy/log_std"), vec![-0.3, 0.5f32.ln(), -0.7]);
    assert_eq!(f32s(&new, "normalizer/obs/mean"), vec![0.1, 0.2, 0.0, 0.3, 0.0]);
    assert_eq!(f32s(&new, "normalizer/obs/std"), vec![2.0, 3.0, 1.0, 4.0, 1.0]);
    // Repeated segments (history of observations): each block grows on its own.
    let (a_old, a_new) = (f32s(&old, "adaptation/hidden_0/kernel"), f32s(&new, "adaptation/hidden_0/kernel"));
    assert_eq!(new.tensors["adaptation/hidden_0/kernel"].shape, vec![HISTORY * 5, HIDDEN]);
    for step in 0..HISTORY {
        for (old_i, new_i) in [(0, 0), (1, 1), (2, 3)] {
            assert_eq!(row(&a_old, step * 3 + old_i), row(&a_new, step * 5 + new_i));
        }
        assert_eq!(row(&a_new, step * 5 + 2), vec![0.0; HIDDEN]);
    }
    // Optimizer moments follow their parameters with zeros; bookkeeping is untouched.
    let m_new = f32s(&new, "opt/policy/mu/hidden_0/kernel");
    assert_eq!(row(&m_new, 3), row(&f32s(&old, "opt/policy/mu/hidden_0/kernel"), 2));
    assert_eq!(row(&m_new, 2), vec![0.0; HIDDEN]);
    assert_eq!(new.tensors["opt/count"], old.tensors["opt/count"]);
    assert_eq!(new.tensors["normalizer/count"], old.tensors["normalizer/count"]);
    assert_eq!(new.tensors["value/hidden_0/kernel"].shape, vec![5 + 1, HIDDEN]);
}

#[test]
fn expanded_actor_keeps_the_old_actions_whatever_the_new_features() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let out = root.path().join("expanded");
    expand(&src, &new_features(), "full", 0.0, &out).unwrap();
    let (old, new) = (load(&src).unwrap(), load(&out).unwrap());
    for trial in 0..20u64 {
        let obs_old = values(3, 100 + trial);
        let latent = values(LATENT, 200 + trial);
        let extra = values(2, 300 + trial).iter().map(|v| v * 50.0).collect::<Vec<_>>();
        let obs_new = vec![obs_old[0], obs_old[1], extra[0], obs_old[2], extra[1]];
        let a_old = actor(&old, &obs_old, &latent);
        let a_new = actor(&new, &obs_new, &latent);
        assert_eq!(a_new.len(), 3);
        assert_eq!([a_new[0], a_new[2]], [a_old[0], a_old[1]], "trial {trial}");
        assert_eq!(a_new[1], f32s(&new, "policy/hidden_1/bias")[1], "the new action's mean is its (zero) bias");
    }
}

#[test]
fn expanding_to_the_same_features_copies_everything() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let out = root.path().join("same");
    let report = expand(&src, &old_features(), "planar", 0.0, &out).unwrap();
    assert!(report.resized.is_empty());
    let (old, new) = (load(&src).unwrap(), load(&out).unwrap());
    assert_eq!(old.tensors, new.tensors);
    assert_eq!(old.meta, new.meta);
}

#[test]
fn reordered_features_move_without_growing() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let out = root.path().join("reordered");
    let target = FeatureNames { obs_names: names(&["c", "g", "a"]), ..old_features() };
    let report = expand(&src, &target, "planar", 0.0, &out).unwrap();
    assert!(report.added_obs.is_empty());
    let new = load(&out).unwrap();
    assert_eq!(f32s(&new, "normalizer/obs/std"), vec![4.0, 2.0, 3.0]);
}

fn expand_err(src: &Path, target: &FeatureNames, out: &Path) -> String {
    expand(src, target, "full", 0.0, out).unwrap_err().to_string()
}

#[test]
fn refusals_say_what_differs() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let out = root.path().join("out");

    let dropped = FeatureNames { obs_names: names(&["g", "b"]), action_names: names(&["A"]), ..old_features() };
    let err = expand_err(&src, &dropped, &out);
    assert!(
        err.ends_with("features of stage planar missing from the target: obs a, c; action C; expansion can add features, never remove them"),
        "{err}"
    );
    assert!(err.starts_with(&format!("cannot expand {} into stage full: ", src.display())), "{err}");
    assert!(!out.exists(), "nothing is written on refusal");

    let twice = FeatureNames { obs_names: names(&["g", "a", "c", "a"]), ..old_features() };
    assert!(expand_err(&src, &twice, &out).contains("obs_names lists \"a\" twice"));

    std::fs::create_dir(&out).unwrap();
    assert_eq!(expand_err(&src, &new_features(), &out), format!("{} already exists; expansion never overwrites a directory", out.display()));
    std::fs::remove_dir(&out).unwrap();

    // A growing axis without a fill.
    let no_fill = root.path().join("no_fill");
    let mut checkpoint = synthetic(&no_fill);
    checkpoint.meta.tensors.get_mut("policy/hidden_1/bias").unwrap().fill = None;
    save(&no_fill, &checkpoint).unwrap();
    let err = expand_err(&no_fill, &new_features(), &out);
    assert!(err.ends_with("tensor policy/hidden_1/bias: axis 0 ([action_names]) changes but the tensor has no \"fill\" for new entries"), "{err}");

    // A growing axis of a boolean tensor.
    let boolean = root.path().join("bool");
    let mut checkpoint = synthetic(&boolean);
    checkpoint.tensors.insert("mask".into(), Tensor { dtype: Dtype::BOOL, shape: vec![3], data: vec![1, 0, 1] });
    checkpoint.meta.tensors.insert("mask".into(), annotation(vec![3], json!([[{"features": "obs"}]]), json!(0)));
    save(&boolean, &checkpoint).unwrap();
    assert!(expand_err(&boolean, &new_features(), &out).contains("tensor mask: an axis of a BOOL tensor cannot grow"));
}

#[test]
fn expand_to_stage_refuses_other_hidden_sizes() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap();
    let curriculum = crate::curriculum::load(&repo.join("tests/data/tiny.toml")).unwrap();
    let err = expand_to_stage(&src, &curriculum.stages()[1], &root.path().join("out")).unwrap_err().to_string();
    assert!(
        err.contains("the network differs (policy_hidden [5] -> [16, 16], value_hidden [5] -> [16, 16], latent_dim 2 -> 4, encoder_hidden [5] -> [16], history_len 3 -> 4)"),
        "{err}"
    );
}

#[test]
fn bad_checkpoints_give_one_line_errors() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let meta_text = std::fs::read_to_string(src.join(META_FILE)).unwrap();
    let params = std::fs::read(src.join(PARAMS_FILE)).unwrap();
    let case = |name: &str, meta: Option<&str>, params: Option<&[u8]>| -> String {
        let dir = root.path().join(name);
        std::fs::create_dir(&dir).unwrap();
        if let Some(meta) = meta {
            std::fs::write(dir.join(META_FILE), meta).unwrap();
        }
        if let Some(params) = params {
            std::fs::write(dir.join(PARAMS_FILE), params).unwrap();
        }
        let err = load(&dir).unwrap_err().to_string();
        assert!(!err.contains('\n'), "{err}");
        err.replace(&dir.display().to_string(), "DIR")
    };
    let missing = root.path().join("missing");
    assert_eq!(load(&missing).unwrap_err().to_string(), format!("{}: no such checkpoint directory", missing.display()));
    assert_eq!(case("empty", None, None), "DIR: not a checkpoint directory (no checkpoint.json)");
    assert_eq!(case("no_params", Some(&meta_text), None), "DIR: not a checkpoint directory (no params.safetensors)");
    assert_eq!(
        case("bad_json", Some("{\"format_version\": 1,\n  oops"), Some(&params)),
        "DIR/checkpoint.json:2:3: corrupt checkpoint metadata: key must be a string"
    );
    assert_eq!(
        case("version", Some(&meta_text.replace("\"format_version\": 1", "\"format_version\": 2")), Some(&params)),
        "DIR/checkpoint.json: unsupported checkpoint format_version 2; this hifar reads format_version 1"
    );
    assert!(case("no_names", Some(&meta_text.replace("\"obs_names\"", "\"obs_nam\"")), Some(&params))
        .starts_with("DIR/checkpoint.json:"));
    assert!(case("truncated", Some(&meta_text), Some(&params[..params.len() - 3]))
        .starts_with("DIR/params.safetensors: corrupt safetensors file: "));
    let shape = meta_text.replacen("\"shape\": [\n        3\n      ]", "\"shape\": [\n        4\n      ]", 1);
    assert_ne!(shape, meta_text, "the fixture has a [3] shape to break");
    let err = case("shape", Some(&shape), Some(&params));
    assert!(err.starts_with("DIR/checkpoint.json: tensor ") && err.contains("covers 3 entries"), "{err}");

    // A tensor the metadata does not describe, and a described tensor that is missing.
    let mut checkpoint = synthetic(&src);
    checkpoint.meta.tensors.remove("opt/count");
    let unannotated = root.path().join("unannotated");
    write_files_into(&unannotated, &checkpoint, &synthetic(&src));
    assert_eq!(load(&unannotated).unwrap_err().to_string(), format!("{}: tensor opt/count has no entry in checkpoint.json", unannotated.join(PARAMS_FILE).display()));
}

/// Writes `meta_from`'s metadata with `tensors_from`'s tensors (to build inconsistent files).
fn write_files_into(dir: &Path, meta_from: &Checkpoint, tensors_from: &Checkpoint) {
    std::fs::create_dir(dir).unwrap();
    let mixed = Checkpoint { meta: meta_from.meta.clone(), tensors: tensors_from.tensors.clone(), ..tensors_from.clone() };
    write_files(dir, &mixed).unwrap();
}

#[test]
fn meta_round_trips_with_extra_keys() {
    let root = tempfile::tempdir().unwrap();
    let src = write_synthetic(root.path());
    let meta = read_meta(&src).unwrap();
    let text = serde_json::to_string(&meta).unwrap();
    let back = parse_meta(Path::new("x"), &text).unwrap();
    assert_eq!(meta, back);
    assert_eq!(back.tensors["policy/log_std"].fill, Some(Fill::Named("log_initial_action_std".into())));
    assert_eq!(back.tensors["policy/hidden_0/kernel"].axes[0], Some(vec![Segment::Features(FeatureKind::Obs), Segment::Fixed(LATENT)]));
}

#[test]
fn an_untrained_adaptation_module_is_not_deployable() {
    let dir = Path::new("runs/r/stages/planar/checkpoints/000000004096");
    let mut meta = synthetic(dir).meta;
    assert!(meta.network.rma);
    let refused = |meta: &CheckpointMeta| check_deployable(dir, meta).map(|_| ()).map_err(|e| e.to_string());

    // No "learner" section (a hand-made checkpoint).
    let err = refused(&meta).unwrap_err();
    assert_eq!(
        err,
        "runs/r/stages/planar/checkpoints/000000004096: its RMA adaptation module was never trained \
         (checkpoint.json has no \"learner\" section recording an adaptation phase); \
         train with rma.adaptation_env_steps > 0 or evaluate a later checkpoint"
    );
    // A stage stopped (or budgeted) before its adaptation phase.
    meta.extra.insert(
        LEARNER_KEY.into(),
        json!({"iteration": 8, "ppo_env_steps": 4096, "adaptation_env_steps": 0, "phase": "done", "adaptation_budget": 0}),
    );
    let err = refused(&meta).unwrap_err();
    assert!(err.contains("was never trained (stage planar ended before its adaptation phase); train with"), "{err}");
    assert_eq!(err.lines().count(), 1);
    // A learner section without the counter.
    meta.extra.insert(LEARNER_KEY.into(), json!({"phase": "ppo"}));
    assert!(refused(&meta).unwrap_err().contains("records no adaptation_env_steps"));
    // A PPO checkpoint of a stage that trains the module beside PPO (ROA): deployable once
    // PPO has run, not before.
    meta.extra.insert(STAGE_CONFIG_KEY.into(), json!({"rma": {"latent_regularization": 0.5}}));
    meta.extra.insert(LEARNER_KEY.into(), json!({"phase": "ppo", "ppo_env_steps": 4096, "adaptation_env_steps": 0}));
    assert_eq!(refused(&meta), Ok(()));
    meta.extra.insert(LEARNER_KEY.into(), json!({"phase": "ppo", "ppo_env_steps": 0, "adaptation_env_steps": 0}));
    assert!(refused(&meta).unwrap_err().contains("ended before its adaptation phase"));
    meta.extra.insert(STAGE_CONFIG_KEY.into(), json!({"rma": {"latent_regularization": 0.0}}));
    meta.extra.insert(LEARNER_KEY.into(), json!({"phase": "ppo", "ppo_env_steps": 4096, "adaptation_env_steps": 0}));
    assert!(refused(&meta).unwrap_err().contains("ended before its adaptation phase"));
    meta.extra.remove(STAGE_CONFIG_KEY);
    // Adapted: deployable.
    meta.extra.insert(LEARNER_KEY.into(), json!({"phase": "done", "adaptation_env_steps": 64}));
    assert_eq!(refused(&meta), Ok(()));
    // Without RMA there is no adaptation module to train.
    meta.extra.remove(LEARNER_KEY);
    meta.network.rma = false;
    assert_eq!(refused(&meta), Ok(()));
}
