use std::path::{Path, PathBuf};

use serde_json::json;

use super::*;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

fn tiny_text() -> String {
    std::fs::read_to_string(repo().join("tests/data/tiny.toml")).unwrap()
}

fn parse_text(text: &str) -> Result<Curriculum, CurriculumError> {
    parse(Path::new("c.toml"), text.to_owned())
}

fn first_error(text: &str) -> String {
    let Err(err) = parse_text(text) else { panic!("the curriculum should be rejected") };
    err.to_string().lines().next().unwrap().to_owned()
}

#[test]
fn tiny_loads_with_two_stages() {
    let c = load(&repo().join("tests/data/tiny.toml")).unwrap();
    assert_eq!(c.name(), "tiny");
    assert_eq!(c.seed(), 7);
    assert_eq!(c.backend(), "native");
    let names: Vec<&str> = c.stages().iter().map(|s| s.name()).collect();
    assert_eq!(names, ["planar", "full"]);
    assert_eq!(c.init_source(0), None);
    assert_eq!(c.init_source(1), Some(0));
    assert_eq!(c.stages()[1].initial_action_std(), 0.5);
    assert_eq!(c.stages()[1].advance().min_stand_rate, Some(0.8));
    assert!(c.stages()[1].advance().on_miss_continue());

    let planar = feature_names(&c.stages()[0]);
    assert_eq!(planar.action_names.len(), 10);
    assert_eq!(planar.action_names[0], "Left_Shoulder_Pitch");
    assert_eq!(planar.obs_names.len(), 6 + 3 * 10);
    let full = feature_names(&c.stages()[1]);
    assert_eq!(full.action_names.len(), 10 + 2);
    assert!(planar.obs_names.iter().all(|n| full.obs_names.contains(n)));
}

#[test]
fn stage_json_is_the_stage_table() {
    let c = parse_text(&tiny_text()).unwrap();
    let stage = c.stages()[0].to_json();
    let keys: Vec<&str> = stage.as_object().unwrap().keys().map(String::as_str).collect();
    assert_eq!(keys[..4], ["name", "init_from", "controlled_joints", "observed_joints"]);
    assert_eq!(keys.len(), 4 + 16);
    assert_eq!(stage["ppo"]["num_envs"], json!(8));
    assert_eq!(stage["ppo"]["learning_rate"], json!(3e-4));
    assert_eq!(stage["scenarios"]["ksi_prone_1"], json!(0.1));
    assert_eq!(stage["scenarios"].as_object().unwrap().len(), 8, "omitted scenarios stay omitted");
    assert_eq!(stage["rewards"]["survival"], json!(0.1));
    assert!(stage["advance"].get("min_stand_rate").is_none(), "optional keys stay absent");
    assert_eq!(
        stage["domain_randomization"]["dof_position"],
        json!({"range": [0.0, 0.05], "operation": "additive", "distribution": "gaussian"})
    );
    assert_eq!(stage["controlled_joints"][1], json!("Left_Elbow_Yaw"));
    // A JSON round trip gives the same typed stage.
    let back: Stage = serde_json::from_value(stage.clone()).unwrap();
    assert_eq!(back.to_json(), stage);

    let resolved = c.resolved_json();
    assert_eq!(resolved["schema_version"], json!(1));
    assert_eq!(resolved["stage"][1], c.stages()[1].to_json());
}

#[test]
fn overrides_apply_and_are_checked() {
    let mut c = parse_text(&tiny_text()).unwrap();
    c.apply_overrides(Some(99), Some("mjx"), Some(16)).unwrap();
    assert_eq!(c.seed(), 99);
    assert_eq!(c.backend(), "mjx");
    assert!(c.stages().iter().all(|s| s.ppo.num_envs == 16));
    assert_eq!(c.stages()[0].to_json()["ppo"]["num_envs"], json!(16));
    assert_eq!(c.resolved_json()["seed"], json!(99));

    let err = c.apply_overrides(None, None, Some(9)).unwrap_err().to_string();
    assert!(err.starts_with("--num-envs 9: stage \"planar\": num_envs = 9 is not divisible by num_minibatches = 2"), "{err}");
    assert!(err.contains("(c.toml:"), "{err}");
    assert!(c.apply_overrides(None, None, Some(0)).is_err());
    let err = c.apply_overrides(None, Some("cuda"), None).unwrap_err().to_string();
    assert_eq!(err, "--backend \"cuda\": expected one of auto, mjx, native");
    assert_eq!(c.stages()[0].ppo.num_envs, 16, "a failed override changes nothing");
}

#[test]
fn python_key_paths_map_to_lines() {
    let text = tiny_text();
    let c = parse_text(&text).unwrap();
    let line_of = |needle: &str, nth: usize| -> (usize, usize) {
        let mut pos = 0;
        for _ in 0..nth {
            pos = text[pos..].find(needle).unwrap() + pos + 1;
        }
        span::line_col(&text, pos - 1)
    };
    let loc = c.locate(0, &[json!("scenarios"), json!("supine")]);
    assert_eq!((loc.line, loc.col), line_of("supine = 0.2", 1));
    assert_eq!(loc.to_string(), format!("c.toml:{}:{}", loc.line, loc.col));
    // The fourth controlled joint of the second stage.
    let loc = c.locate(1, &[json!("controlled_joints"), json!(3)]);
    assert_eq!((loc.line, loc.col), line_of("\"Right_Elbow_Yaw\"", 3));
    // A key that is not in the file points at its table.
    let loc = c.locate(1, &[json!("ppo"), json!("no_such_key")]);
    assert_eq!((loc.line, loc.col), line_of("[stage.ppo]", 2));
    // An empty path points at the stage's [[stage]] header.
    let loc = c.locate(1, &[]);
    assert_eq!((loc.line, loc.col), line_of("[[stage]]", 2));
}

/// Every fixture in tests/data/bad names its expected first error in its second line:
/// `# expect: LINE:COL: fragment of the message`. Those whose error is a stage's meaning pass
/// `load` and are rejected by Python (`hifar check`, tests/cli/curriculum.rs runs them all);
/// every one `load` rejects must be rejected at its line, and the ones it owns (syntax, types,
/// names, references between stages) are most of them.
#[test]
fn bad_fixtures_report_the_offending_line() {
    let dir = repo().join("tests/data/bad");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.retain(|p| p.extension().is_some_and(|e| e == "toml"));
    files.sort();
    assert!(files.len() >= 20, "fixtures missing in {}", dir.display());
    let mut failures = Vec::new();
    let mut rejected = 0;
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        let expect = text.lines().nth(1).and_then(|l| l.strip_prefix("# expect: ")).expect("an expect line");
        let (position, fragment) = expect.split_once(": ").unwrap();
        let Err(err) = load(file) else { continue };
        rejected += 1;
        let first = err.to_string().lines().next().unwrap().to_owned();
        let prefix = format!("{}:{position}: ", file.display());
        if !first.starts_with(&prefix) || !first.contains(fragment) {
            failures.push(format!("{}\n  expected {prefix}…{fragment}…\n  got      {first}", file.display()));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(rejected >= 17, "only {rejected} fixtures rejected before Python");
}

#[test]
fn all_problems_are_reported_in_file_order() {
    let text = tiny_text()
        .replacen("learning_rate = 3e-4", "learning_rate = inf", 1)
        .replacen("init_from = \"planar\"", "init_from = \"walking\"", 1)
        .replacen("num_envs = 8", "num_envs = -1", 1);
    let err = parse_text(&text).unwrap_err();
    assert_eq!(err.problems.len(), 1, "types first: {err}");
    let text = tiny_text()
        .replacen("learning_rate = 3e-4", "learning_rate = inf", 2)
        .replacen("init_from = \"planar\"", "init_from = \"walking\"", 1);
    let err = parse_text(&text).unwrap_err();
    let lines: Vec<(usize, usize)> = err.problems.iter().map(|p| p.line.unwrap()).collect();
    assert_eq!(err.problems.len(), 3, "{err}");
    assert!(lines.windows(2).all(|w| w[0] <= w[1]), "{lines:?}");
    assert!(err.problems[0].message.contains("learning_rate = inf must be a finite number"));
    assert!(err.problems[1].message.contains("init_from = \"walking\""));
    assert!(err.problems[2].message.contains("learning_rate = inf"));
}

#[test]
fn more_rejections() {
    let tiny = tiny_text();
    let cases: &[(&str, &str, &str)] = &[
        ("init_from = \"none\"", "init_from = \"previous\"", "there is no previous stage"),
        ("init_from = \"planar\"", "init_from = \"full\"", "cannot start from itself"),
        ("learning_rate = 3e-4", "learning_rate = nan", "learning_rate = NaN must be a finite number"),
        ("range = [0.0, 0.05]", "range = [0.0, inf]", "dof_position.range = [0, inf] must hold finite numbers"),
        ("interval_s = [2.0, 4.0]", "interval_s = [-inf, 4.0]", "interval_s = [-inf, 4]: both must be finite"),
        ("survival = 0.1", "survival = nan", "reward weight survival = NaN must be a finite number"),
        ("supine = 0.2", "supine = inf", "scenario weight supine = inf must be a finite number >= 0"),
        ("num_envs = 8", "num_envs = -8", "invalid value: integer `-8`, expected a non-negative integer"),
        ("num_envs = 8", "num_envs = 8.0", "invalid type: floating point `8.0`, expected a non-negative integer"),
        ("range = [0.0, 0.05]", "range = [0.0, 0.05, 1.0]", "invalid length 3"),
        ("name = \"tiny\"", "name = \"my run\"", "must match [A-Za-z0-9_-]+"),
        ("backend = \"native\"", "backend = \"gpu\"", "unknown value `gpu` for backend; expected one of `auto`, `mjx`, `native`"),
    ];
    for (old, new, fragment) in cases {
        assert!(tiny.contains(old), "{old}");
        let message = first_error(&tiny.replacen(old, new, 1));
        assert!(message.contains(fragment), "{new}: {message}");
        assert!(message.starts_with("c.toml:"), "{message}");
    }
    // No stages at all.
    let head = &tiny[..tiny.find("[[stage]]").unwrap()];
    assert!(first_error(head).contains("missing required key `stage` in the top level"), "{}", first_error(head));
    // No schema_version.
    let text = tiny.replacen("schema_version = 1\n", "", 1);
    assert_eq!(first_error(&text), "c.toml:1:1: missing schema_version; this hifar reads schema_version = 1 (add it as the first line)");
    // A stage that drops a joint of the stage it starts from.
    let text = tiny.replacen(
        "controlled_joints = [\n  \"Left_Shoulder_Pitch\", \"Left_Elbow_Yaw\", \"Right_Shoulder_Pitch\", \"Right_Elbow_Yaw\",\n  \"Left_Hip_Pitch\", \"Left_Hip_Roll\"",
        "controlled_joints = [\n  \"Left_Shoulder_Pitch\", \"Right_Shoulder_Pitch\",\n  \"Left_Hip_Pitch\", \"Left_Hip_Roll\"",
        1,
    );
    assert!(first_error(&text).contains("drops controlled_joints Left_Elbow_Yaw, Right_Elbow_Yaw"), "{}", first_error(&text));
}

#[test]
fn unreadable_file() {
    let err = load(Path::new("/nonexistent/c.toml")).unwrap_err().to_string();
    assert!(err.starts_with("/nonexistent/c.toml: cannot read the curriculum: "), "{err}");
}

#[test]
fn shipped_curricula_are_valid() {
    for name in ["curricula/hifar.toml", "curricula/quickstart.toml", "curricula/cpu.toml"] {
        let c = load(&repo().join(name)).unwrap_or_else(|e| panic!("{e}"));
        let names: Vec<&str> = c.stages().iter().map(|s| s.name()).collect();
        assert_eq!(names, ["planar", "full"], "{name}");
        assert_eq!(c.init_source(1), Some(0));
        let (planar, full) = (&c.stages()[0], &c.stages()[1]);
        assert_eq!(feature_names(planar).action_names.len(), 10);
        assert_eq!(feature_names(full).action_names.len(), 12);
        assert_eq!(full.domain_randomization.params().len(), 12, "{name}: stage 2 uses the whole DR table");
    }
}

/// tiny.toml with every optional key of the issue-10 additions set in its first stage.
fn tiny_with_new_keys() -> String {
    let tiny = tiny_text();
    let second = tiny.find("[[stage]]\nname = \"full\"").unwrap();
    let (first, rest) = tiny.split_at(second);
    let first = first
        .replacen("prone = 0.2\n", "prone = 0.1\nstand = 0.05\nsquat = 0.05\n", 1)
        .replacen("action_rate = -0.001\n", "action_rate = -0.001\ntrunk_height = 1.0\nwaist_height = 0.5\nupright = 0.2\n", 1)
        .replacen("hip_roll_ref = 0.0\n", "hip_roll_ref = 0.0\nwaist_height_target = 0.55\ndof_pos_ref_band = 0.1\nface_down_gate = [0.3, 0.6]\nhead_down_gate = [0.0, 0.5]\n", 1)
        .replacen("checkpoint_every = 2\n", "checkpoint_every = 2\nmax_action_std = 1.5\naction_std_schedule = { by='env_steps', points = [[100, 1.0], [3_000, 0.1]] }\naction_noise_correlation = 0.9\n", 1);
    format!(
        "{first}[stage.reward_shaping]\nscale_by_ctrl_dt = true\nclip_at_zero = false\n\
         penalty_schedule = {{ by = \"env_steps\", points = [[0, 0.1], [1_000, 1.0]] }}\n\n\
         [stage.termination]\nlow_height = 0.2\nlow_height_s = 1.0\nupside_down = 0.5\nside_roll = 0.0\n\n\
         [stage.monitor]\nevery = 10\nepisodes = 4\nscenarios = [\"supine\", \"stand\", \"squat\"]\nkeep_best = true\n\n\
         [stage.assist]\nforce = 150.0\nschedule = {{ by = \"stand_rate\", points = [[0, 1.0], [0.5, 0.0]] }}\n\n\
         [stage.imitation]\nweight = 2.0\nforcing = 0.5\nschedule = {{ by = \"env_steps\", points = [[0, 1.0], [2_000, 0.0]] }}\n\n{rest}"
    )
}

#[test]
fn new_optional_keys_parse_and_reach_python_as_written() {
    let text = tiny_with_new_keys();
    let c = parse_text(&text).unwrap_or_else(|e| panic!("{e}"));
    let stage = c.stages()[0].to_json();
    assert_eq!(stage["scenarios"]["stand"], json!(0.05));
    assert_eq!(stage["scenarios"]["squat"], json!(0.05));
    for (term, weight) in [("trunk_height", 1.0), ("waist_height", 0.5), ("upright", 0.2)] {
        assert_eq!(stage["rewards"][term], json!(weight), "{term}");
    }
    assert_eq!(stage["reward_params"]["waist_height_target"], json!(0.55));
    assert_eq!(stage["reward_params"]["dof_pos_ref_band"], json!(0.1));
    assert_eq!(stage["reward_params"]["face_down_gate"], json!([0.3, 0.6]));
    assert_eq!(stage["reward_params"]["head_down_gate"], json!([0.0, 0.5]));
    assert_eq!(stage["ppo"]["max_action_std"], json!(1.5));
    assert_eq!(stage["ppo"]["action_noise_correlation"], json!(0.9));
    assert_eq!(stage["ppo"]["action_std_schedule"], json!({"by": "env_steps", "points": [[100.0, 1.0], [3000.0, 0.1]]}));
    assert_eq!(
        stage["reward_shaping"],
        json!({"scale_by_ctrl_dt": true, "clip_at_zero": false,
               "penalty_schedule": {"by": "env_steps", "points": [[0.0, 0.1], [1000.0, 1.0]]}})
    );
    assert_eq!(stage["termination"], json!({"low_height": 0.2, "low_height_s": 1.0, "upside_down": 0.5, "side_roll": 0.0}));
    assert_eq!(stage["monitor"], json!({"every": 10, "episodes": 4, "scenarios": ["supine", "stand", "squat"], "keep_best": true}));
    assert_eq!(
        stage["assist"],
        json!({"force": 150.0, "schedule": {"by": "stand_rate", "points": [[0.0, 1.0], [0.5, 0.0]]}})
    );
    assert_eq!(
        stage["imitation"],
        json!({"weight": 2.0, "forcing": 0.5, "schedule": {"by": "env_steps", "points": [[0.0, 1.0], [2000.0, 0.0]]}})
    );
    // A JSON round trip gives the same stage.
    let back: Stage = serde_json::from_value(stage.clone()).unwrap();
    assert_eq!(back.to_json(), stage);

    // Partial tables give back only their keys; the second stage sets none of them.
    let text = text.replacen("scale_by_ctrl_dt = true\nclip_at_zero = false\n", "", 1).replacen("episodes = 4\n", "", 1).replacen("keep_best = true\n", "", 1);
    let c = parse_text(&text).unwrap_or_else(|e| panic!("{e}"));
    let stage = c.stages()[0].to_json();
    assert_eq!(stage["reward_shaping"].as_object().unwrap().keys().collect::<Vec<_>>(), ["penalty_schedule"]);
    assert_eq!(stage["monitor"].as_object().unwrap().keys().collect::<Vec<_>>(), ["every", "scenarios"]);
    let full = c.stages()[1].to_json();
    for key in ["reward_shaping", "termination", "monitor", "assist", "imitation"] {
        assert!(full.get(key).is_none(), "{key} stays absent");
    }
    assert!(full["ppo"].get("max_action_std").is_none());
    assert!(full["ppo"].get("action_noise_correlation").is_none());
    assert!(full["ppo"].get("action_std_schedule").is_none());
    assert!(full["reward_params"].get("waist_height_target").is_none());
    assert!(full["reward_params"].get("dof_pos_ref_band").is_none());
    assert!(full["reward_params"].get("face_down_gate").is_none());
}

#[test]
fn mistakes_in_the_new_tables_have_a_position() {
    let text = tiny_with_new_keys();
    let cases: &[(&str, &str, &str, &str)] = &[
        ("low_height_s = 1.0", "low_heigth_s = 1.0", "low_heigth_s", "unknown key `low_heigth_s` in [stage.termination]; valid keys: `low_height`, `low_height_s`, `upside_down`, `upside_down_face_down`, `upside_down_face_down_max_roll`, `side_roll`"),
        ("clip_at_zero = false", "clip_at_zero = 0", "clip_at_zero", "reward_shaping.clip_at_zero: invalid type: integer `0`, expected a boolean"),
        ("episodes = 4", "episodes = -4", "episodes", "monitor.episodes: invalid value: integer `-4`, expected a non-negative integer"),
        ("keep_best = true", "keep_best = 1", "keep_best", "monitor.keep_best: invalid type: integer `1`, expected a boolean"),
        ("\"stand\", \"squat\"]", "\"standing\", \"squat\"]", "\"standing\"", "unknown value `standing` for stage.monitor.scenarios[1]"),
        ("by = \"env_steps\"", "by = \"steps\"", "by = ", "unknown value `steps` for stage.reward_shaping.penalty_schedule.by; expected one of `env_steps` or `stand_rate`"),
        ("[1_000, 1.0]]", "[1_000, 1.0, 2.0]]", "penalty_schedule", "invalid length 3, expected an array of two numbers [x, scale]"),
        ("points = [[0", "point = [[0", "penalty_schedule", "unknown key `point` in [stage.reward_shaping.penalty_schedule]; valid keys: `by` or `points`"),
        ("force = 150.0", "force = \"strong\"", "force = \"strong", "assist.force: invalid type: string \"strong\", expected a number"),
        ("forcing = 0.5", "forcng = 0.5", "forcng", "unknown key `forcng` in [stage.imitation]"),
        ("max_action_std = 1.5", "max_action_std = \"big\"", "max_action_std", "ppo.max_action_std: invalid type: string \"big\", expected a number"),
        ("[3_000, 0.1]", "[3_000, 0.1, 1.0]", "action_std_schedule", "invalid length 3, expected an array of two numbers [x, scale]"),
        ("by='env_steps'", "by='steps'", "by='steps'", "unknown value `steps` for stage.ppo.action_std_schedule.by"),
        ("face_down_gate = [0.3, 0.6]", "face_down_gate = [0.3]", "face_down_gate", "invalid length 1, expected an array of two numbers [min, max]"),
        ("waist_height = 0.5", "waist_hieght = 0.5", "waist_hieght", "unknown reward term `waist_hieght` in [stage.rewards]"),
    ];
    for (old, new, at, fragment) in cases {
        assert!(text.contains(old), "{old}");
        let bad = text.replacen(old, new, 1);
        let message = first_error(&bad);
        let line = bad[..bad.find(at).unwrap()].matches('\n').count() + 1;
        assert!(message.starts_with(&format!("c.toml:{line}:")), "{new}: {message} (expected line {line})");
        assert!(message.contains(fragment), "{new}: {message}");
    }
}
