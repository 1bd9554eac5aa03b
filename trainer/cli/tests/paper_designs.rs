//! The LMAC authors' designs shipped in `protocols/paper/`: every one compiles against its env's
//! schema within the budget, each field reads exactly the observation dims (and previous action,
//! sender id, history depth) that the authors' code reads, listed below by hand from their
//! `src/llm_source_archive/<task>/*.py`, and `paper` / `paper:<task>` protocol specs find them.

use lmac_protocol_runner::protocol::{self, Expr};
use lmac_run::train::{paper_designs_dir, protocol_files, TrainConfig};
use std::collections::BTreeSet;

/// What one field reads: observation dims, whether the previous action and the sender's id
/// enter it, and its deepest window (0: the current step only).
#[derive(Debug, PartialEq, Eq, Default)]
struct Reads {
    obs: BTreeSet<usize>,
    last_action: bool,
    sender_id: bool,
    depth: usize,
}

fn reads(e: &Expr, r: &mut Reads) {
    match e {
        Expr::Obs(d) => r.obs.extend(d.iter().copied()),
        Expr::ObsSlice(s) => r.obs.extend(s.start..s.end),
        Expr::LastAction(_) => r.last_action = true,
        Expr::SenderOneHot => r.sender_id = true,
        Expr::Const(_) => {}
        Expr::Window(w) => {
            r.depth = r.depth.max(w.k);
            reads(&w.of, r);
        }
        Expr::Neg(a) | Expr::Abs(a) => reads(a, r),
        Expr::Clip(c) => reads(&c.of, r),
        Expr::Reduce(x) => reads(&x.of, r),
        Expr::Concat(v) => v.iter().for_each(|x| reads(x, r)),
        other => {
            let (_, a, b) = other.binary().expect("every other expression is binary");
            reads(a, r);
            reads(b, r);
        }
    }
}

const LA: u8 = 1;
const ID: u8 = 2;

/// (env, phase, field, obs dims, LA/ID flags, deepest window), by hand from the authors' code:
/// their per-agent input is [obs | previous action one-hot | agent id one-hot], so their indices
/// past obs_dim are the previous action (LA) or the id (ID); their obs order is ours for SMAC and
/// GRF, and for LBF their 27 grid values are our obs 0-26.
fn table() -> Vec<(&'static str, usize, &'static str, Vec<usize>, u8, usize)> {
    let r = |a: usize, b: usize| (a..b).collect::<Vec<_>>();
    let o10b_rel: Vec<usize> = (0..10).flat_map(|i| [14 + 7 * i, 15 + 7 * i]).collect();
    let o10b_vis: Vec<usize> = (0..10).map(|i| 12 + 7 * i).collect();
    let roach2 = vec![4, 6, 7, 12, 14, 15];
    let z_first_teammate = vec![10, 12, 13, 16, 18, 19, 22, 24, 25, 28, 30, 31];
    let mut z_placed = vec![4, 5, 6, 8, 9];
    z_placed.extend(&z_first_teammate);
    let lbf_ring = vec![0, 1, 2, 3, 5, 6, 7, 8];
    let lbf_food_ring: Vec<usize> = lbf_ring.iter().map(|c| 9 + c).collect();
    let mut t = vec![
        // 1o_10b_vs_1r: comm_init reads Overseer o[6], o[7], o[4] and a fixed one-hot of agent 10.
        ("smaclite:1o_10b_vs_1r", 0, "overseer_roach", vec![4, 6, 7], ID, 0),
        // comm_update: o[85:92] (previous action), o[14+7i], o[15+7i].
        ("smaclite:1o_10b_vs_1r", 1, "overseer_last_action", vec![], LA, 0),
        ("smaclite:1o_10b_vs_1r", 1, "overseer_to_banelings", o10b_rel, 0, 0),
        // timestep_wise2: zeros, o[6:8], o[4] over the window from t-9 (their max index, 0 at t-9,
        // adds nothing: our deepest term is t-8), o[12+7i].
        ("smaclite:1o_10b_vs_1r", 2, "overseer_anchor", vec![], 0, 0),
        ("smaclite:1o_10b_vs_1r", 2, "roach_from_anchor", vec![6, 7], 0, 0),
        ("smaclite:1o_10b_vs_1r", 2, "roach_recency", vec![4], 0, 9),
        ("smaclite:1o_10b_vs_1r", 2, "baneling_visible", o10b_vis, 0, 0),
        // 2o_20b_vs_2r: [4,6,7], [12,14,15], o[178:200] (id).
        ("smaclite:2o_20b_vs_2r", 0, "roaches", roach2.clone(), ID, 0),
        // o[0:4], o[170:178] (previous action).
        ("smaclite:2o_20b_vs_2r", 1, "overseer_moves", r(0, 4), 0, 0),
        ("smaclite:2o_20b_vs_2r", 1, "overseer_last_action", vec![], LA, 0),
        // o[:, 0, 162:164]: the window's oldest step, t-9.
        ("smaclite:2o_20b_vs_2r", 2, "anchor", vec![162, 163], 0, 10),
        // 5z_vs_1ul: o[5:8] * o[4], o[34], o[36:43] (previous action), o[43:48] (id).
        ("smaclite:5z_vs_1ul", 0, "ultralisk", vec![4, 5, 6, 7], 0, 0),
        ("smaclite:5z_vs_1ul", 0, "own_health", vec![34], 0, 0),
        ("smaclite:5z_vs_1ul", 0, "last_action", vec![], LA, 0),
        ("smaclite:5z_vs_1ul", 0, "sender_id", vec![], ID, 0),
        // comm_update: the first visible teammate slot (start = 10 + 6 s: flag, +2, +3), o[35],
        // o[4] with o[42], o[37] (previous action attack / stop), o[5:7], o[8], o[9].
        ("smaclite:5z_vs_1ul", 1, "own_position", z_first_teammate, 0, 0),
        ("smaclite:5z_vs_1ul", 1, "own_shield", vec![35], 0, 0),
        ("smaclite:5z_vs_1ul", 1, "ready", vec![4], LA, 0),
        ("smaclite:5z_vs_1ul", 1, "ultralisk_placed", z_placed, 0, 0),
        // timestep_wise2: o[0], o[1], o[34], o[35], o[36] (previous action column 0), t-9 .. t-1.
        ("smaclite:5z_vs_1ul", 2, "hist_obs0", vec![0], 0, 10),
        ("smaclite:5z_vs_1ul", 2, "hist_obs1", vec![1], 0, 10),
        ("smaclite:5z_vs_1ul", 2, "hist_health", vec![34], 0, 10),
        ("smaclite:5z_vs_1ul", 2, "hist_shield", vec![35], 0, 10),
        ("smaclite:5z_vs_1ul", 2, "hist_noop", vec![], LA, 10),
        // bane_vs_hM: o[6], o[7], o[29], o[39:42] (id).
        ("smaclite:bane_vs_hM", 0, "hydralisk_and_self", vec![6, 7, 29], ID, 0),
        // o[4], o[16], o[22], o[0:4], zeros, o[31:38] (previous action).
        ("smaclite:bane_vs_hM", 1, "flags", vec![4, 16, 22], 0, 0),
        ("smaclite:bane_vs_hM", 1, "moves", r(0, 4), 0, 0),
        ("smaclite:bane_vs_hM", 1, "timestamp", vec![], 0, 0),
        ("smaclite:bane_vs_hM", 1, "last_action_7", vec![], LA, 0),
        // o[0:4] and o[37], o[31] (previous action) averaged over T = 10; o[16], o[18:20]; a constant.
        ("smaclite:bane_vs_hM", 2, "move_rates", r(0, 4), 0, 10),
        ("smaclite:bane_vs_hM", 2, "attack_rate", vec![], LA, 10),
        ("smaclite:bane_vs_hM", 2, "noop_rate", vec![], LA, 10),
        ("smaclite:bane_vs_hM", 2, "teammate0", vec![16, 18, 19], 0, 0),
        ("smaclite:bane_vs_hM", 2, "freshness", vec![], 0, 0),
        // Foraging-8x8: id, o[27:33] (previous action), o[9:18], o[18:27].
        ("lbf:8x8-2p-2f-s1-coop", 0, "sender_id", vec![], ID, 0),
        ("lbf:8x8-2p-2f-s1-coop", 0, "last_action", vec![], LA, 0),
        ("lbf:8x8-2p-2f-s1-coop", 0, "food_view", r(9, 18), 0, 0),
        ("lbf:8x8-2p-2f-s1-coop", 0, "access_view", r(18, 27), 0, 0),
        // comm_update: zeros.
        ("lbf:8x8-2p-2f-s1-coop", 1, "position", vec![], 0, 0),
        // timestep_wise2: o[27:33] summed over 10 steps; non-centre cells of o[9:18] and o[0:9]
        // over the 10-step window; a constant.
        ("lbf:8x8-2p-2f-s1-coop", 2, "action_counts", vec![], LA, 10),
        ("lbf:8x8-2p-2f-s1-coop", 2, "food_seen", lbf_food_ring.clone(), 0, 10),
        ("lbf:8x8-2p-2f-s1-coop", 2, "agent_seen", lbf_ring.clone(), 0, 10),
        ("lbf:8x8-2p-2f-s1-coop", 2, "timestamp", vec![], 0, 0),
        // Foraging-11x11: id, o[9:18], o[18:27], o[27:33].
        ("lbf:11x11-6p-4f-s1-coop", 0, "sender_id", vec![], ID, 0),
        ("lbf:11x11-6p-4f-s1-coop", 0, "food_view", r(9, 18), 0, 0),
        ("lbf:11x11-6p-4f-s1-coop", 0, "access_view", r(18, 27), 0, 0),
        ("lbf:11x11-6p-4f-s1-coop", 0, "last_action", vec![], LA, 0),
        // comm_update: o[0], o[1] (its default pos_x_idx, pos_y_idx).
        ("lbf:11x11-6p-4f-s1-coop", 1, "position", vec![0, 1], 0, 0),
        // timestep_wise2: o[27:32] at t-2, t-1, t; o[9:18] at t-2, t-1; non-centre o[0:9] at t-2 .. t.
        ("lbf:11x11-6p-4f-s1-coop", 2, "track", vec![], LA, 3),
        ("lbf:11x11-6p-4f-s1-coop", 2, "food_history", r(9, 18), 0, 3),
        ("lbf:11x11-6p-4f-s1-coop", 2, "agent_history", lbf_ring, 0, 3),
        // academy_3_vs_1_with_keeper: o[0:2], o[6:8], o[20:22], o[23:25], o[2:6], o[12:16],
        // o[43], o[35:38], o[38], o[39] (previous action), id.
        ("grf:academy_3_vs_1_with_keeper", 0, "ego", vec![0, 1, 6, 7], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 0, "ball", vec![20, 21, 23, 24], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 0, "others", vec![2, 3, 4, 5, 12, 13, 14, 15], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 0, "action_flags", vec![], LA, 0),
        ("grf:academy_3_vs_1_with_keeper", 0, "sender_id", vec![], ID, 0),
        // comm_update: o[0:2] + o[20:22], o[22]; + o[12:16]; + o[2:6]; o[26:45] weighted; o[45:48] (id).
        ("grf:academy_3_vs_1_with_keeper", 1, "ball_abs", vec![0, 1, 20, 21, 22], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 1, "opponents_abs", vec![0, 1, 12, 13, 14, 15], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 1, "teammates_abs", r(0, 6), 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 1, "action_score", vec![], LA, 0),
        ("grf:academy_3_vs_1_with_keeper", 1, "cm_flags", vec![], ID, 0),
        // timestep_wise2: o[8:12]; |o[2:4]|, |o[4:6]|; o[0:2] + o[2:4], o[4:6] over T = 10;
        // |o[12:14]|, |o[14:16]|; |o[20:22]|; o[0:2] + o[20:22] over T; o[0:2] over T.
        ("grf:academy_3_vs_1_with_keeper", 2, "teammate_dirs", r(8, 12), 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 2, "teammate_seen", r(2, 6), 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 2, "teammate_vel", r(0, 6), 0, 10),
        ("grf:academy_3_vs_1_with_keeper", 2, "opponent_seen", r(12, 16), 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 2, "ball_seen", vec![20, 21], 0, 0),
        ("grf:academy_3_vs_1_with_keeper", 2, "ball_vel", vec![0, 1, 20, 21], 0, 10),
        ("grf:academy_3_vs_1_with_keeper", 2, "ego_vel", vec![0, 1], 0, 10),
        // academy_run_pass_and_shoot_with_keeper: o[0:2], o[4:6], o[16:18], o[19:22], o[22:41]
        // (previous action), o[10:12], o[14:16], o[8:10], id.
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "ego", vec![0, 1, 4, 5], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "ball", vec![16, 17, 19, 20, 21], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "last_action", vec![], LA, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "centre_back", vec![10, 11, 14, 15], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "goalkeeper", vec![8, 9], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 0, "sender_id", vec![], ID, 0),
        // comm_update: o[0:2] + o[8:10], o[12:14]; (o[0:2] + o[10:12], o[14:16]) x o[41] / o[42]
        // (id); o[0:2] + o[16:18].
        ("grf:academy_run_pass_and_shoot_with_keeper", 1, "goalkeeper", vec![0, 1, 8, 9, 12, 13], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 1, "centre_back_slot0", vec![0, 1, 10, 11, 14, 15], ID, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 1, "centre_back_slot1", vec![0, 1, 10, 11, 14, 15], ID, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 1, "ball_abs", vec![0, 1, 16, 17], 0, 0),
        // timestep_wise2: now minus t-3 (back_t = window - 4) of o[0:2], o[4:6] and o[2:4], o[6:8];
        // |o[10:12]| + |o[14:16]|; o[18]; ball (o[0:2] + o[16:18], o[18]) change; o[22:41] mean over 10.
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "ego_change", vec![0, 1, 4, 5], 0, 4),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "teammate", vec![2, 3, 6, 7], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "teammate_change", vec![2, 3, 6, 7], 0, 4),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "cb_flags", vec![10, 11, 14, 15], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "ball_height", vec![18], 0, 0),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "ball_change", vec![0, 1, 16, 17, 18], 0, 4),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "action_rates", vec![], LA, 10),
        ("grf:academy_run_pass_and_shoot_with_keeper", 2, "seen_flags", vec![2, 3, 6, 7, 10, 11, 14, 15], 0, 0),
    ];
    // 2o_20b timestep_wise2: per past step j = 9..1 the previous action and both Roaches' readings.
    const HISTORY: [&str; 9] =
        ["history_t9", "history_t8", "history_t7", "history_t6", "history_t5", "history_t4", "history_t3", "history_t2", "history_t1"];
    for (i, name) in HISTORY.iter().enumerate() {
        t.push(("smaclite:2o_20b_vs_2r", 2, *name, roach2.clone(), LA, 10 - i));
    }
    t
}

/// The eight tasks of the authors' archive, by our env name.
const ENVS: [&str; 8] = [
    "grf:academy_3_vs_1_with_keeper",
    "grf:academy_run_pass_and_shoot_with_keeper",
    "lbf:11x11-6p-4f-s1-coop",
    "lbf:8x8-2p-2f-s1-coop",
    "smaclite:1o_10b_vs_1r",
    "smaclite:2o_20b_vs_2r",
    "smaclite:5z_vs_1ul",
    "smaclite:bane_vs_hM",
];

#[test]
fn every_paper_design_compiles_and_reads_the_dims_of_the_authors_code() {
    let root = paper_designs_dir().unwrap();
    let table = table();
    let mut seen_envs = Vec::new();
    let mut checked = 0;
    for entry in std::fs::read_dir(&root).unwrap_or_else(|e| panic!("{}: {e}", root.display())) {
        let dir = entry.unwrap().path();
        if !dir.is_dir() {
            continue;
        }
        let options: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.join("options.json")).unwrap()).unwrap();
        let env = options["env"].as_str().unwrap().to_string();
        assert_eq!(dir.file_name().unwrap().to_str().unwrap(), env.replace(':', "_"), "a design's folder is its env's name");
        let schema = lmac_shm_schema::schema::load_env(&env).unwrap();
        let penv = lmac_protocol_runner::protocol_env(&schema);
        let files = protocol_files(dir.to_str().unwrap(), None).unwrap();
        assert_eq!(files.len(), 3, "{env}: three phases");
        let refs: Vec<&str> = files.iter().map(String::as_str).collect();
        let phases = lmac_protocol_runner::load_phases(&refs, &penv).unwrap_or_else(|e| panic!("{env}: {e}"));
        let width = protocol::check_phases(&phases, &penv).unwrap_or_else(|e| panic!("{env}: {}", protocol::errors_to_text(&e)));
        assert!(width > 0 && width <= schema.message_columns, "{env}: {width} columns, budget {}", schema.message_columns);
        protocol::compile_plan(&phases, &penv).unwrap_or_else(|e| panic!("{env}: {}", protocol::errors_to_text(&e)));
        // One critical set (theirs has one per task), the same in every phase.
        assert!(!phases[0].critical_dims.is_empty(), "{env}: critical dims");
        assert!(phases.iter().all(|p| p.critical_dims == phases[0].critical_dims), "{env}: one critical set");
        for (k, phase) in phases.iter().enumerate() {
            assert_eq!(phase.protocol.phase, Some(k as u32), "{env}: phase number");
            assert!(dir.join(format!("phase{k}")).join("source.txt").is_file(), "{env}: phase {k} names its archive file");
            let rows: Vec<_> = table.iter().filter(|r| r.0 == env && r.1 == k).collect();
            assert_eq!(rows.len(), phase.protocol.fields.len(), "{env} phase {k}: a table row per field");
            for f in &phase.protocol.fields {
                let row =
                    rows.iter().find(|r| r.2 == f.name).unwrap_or_else(|| panic!("{env} phase {k}: field {} not in the table", f.name));
                let mut got = Reads::default();
                reads(&f.value, &mut got);
                let want =
                    Reads { obs: row.3.iter().copied().collect(), last_action: row.4 & LA != 0, sender_id: row.4 & ID != 0, depth: row.5 };
                assert_eq!(got, want, "{env} phase {k} field {}", f.name);
                checked += 1;
            }
        }
        seen_envs.push(env);
    }
    seen_envs.sort();
    assert_eq!(seen_envs, ENVS, "one shipped design per task of the archive");
    assert_eq!(checked, table.len(), "every table row matched a field");
}

fn config(env: &str, protocol: &str) -> anyhow::Result<TrainConfig> {
    TrainConfig::resolve(None, &[format!("run.env={env:?}"), "run.algo=\"lmac\"".into(), format!("run.protocol={protocol:?}")])
}

#[test]
fn paper_specs_find_the_shipped_design_or_name_the_env() {
    let root = paper_designs_dir().unwrap();
    let want: Vec<String> =
        (0..3).map(|k| root.join("smaclite_1o_10b_vs_1r").join(format!("phase{k}")).join("protocol.json").display().to_string()).collect();
    // By archive task, by env, and `paper` for the run's env: the same three files.
    for spec in ["paper:1o_10b_vs_1r", "paper:smaclite:1o_10b_vs_1r", "paper"] {
        let c = config("smaclite:1o_10b_vs_1r", spec).unwrap_or_else(|e| panic!("{spec}: {e:#}"));
        assert_eq!(c.protocol().unwrap().to_string(), want.join("+"), "{spec}");
    }
    let lbf = config("lbf:8x8-2p-2f-s1-coop", "paper:Foraging-8x8-2p-2f-s1True").unwrap();
    assert!(lbf.protocol().unwrap().to_string().contains("lbf_8x8-2p-2f-s1-coop/phase2/protocol.json"));
    // design_k picks the first phases, as for any design directory.
    let mut k0 = config("smaclite:1o_10b_vs_1r", "paper").unwrap();
    k0.run.design_k = Some(0);
    assert_eq!(k0.protocol().unwrap().to_string(), want[0]);

    // No design for this env: the error names it.
    let e = format!("{:#}", config("lbf:8x8-2p-2f-s1-coop-entity", "paper").unwrap_err());
    assert!(e.contains("no paper design is shipped for lbf:8x8-2p-2f-s1-coop-entity"), "{e}");
    let e = format!("{:#}", config("smaclite:1o_10b_vs_1r", "paper:3m").unwrap_err());
    assert!(e.contains("\"3m\"") && e.contains("1o_10b_vs_1r (smaclite:1o_10b_vs_1r)"), "{e}");
    // Another task's design on this env: refused by the design's env.
    let e = format!("{:#}", config("smaclite:1o_10b_vs_1r", "paper:bane_vs_hM").unwrap_err());
    assert!(e.contains("was made for smaclite:bane_vs_hM"), "{e}");
    // The same map with other unit data observes the same values: its design runs there.
    let liberty = config("smaclite:1o_10b_vs_1r-liberty", "paper:1o_10b_vs_1r").unwrap();
    assert_eq!(liberty.protocol().unwrap().to_string(), want.join("+"));
    // Without the state's last actions (the authors' 71-value state) the design's critical dims
    // (62, 63, 67, 68) still mean the same, so it runs there too, and the run checks out.
    for env in ["smaclite:1o_10b_vs_1r-no-last-action", "smaclite:1o_10b_vs_1r-liberty-no-last-action"] {
        let short = config(env, "paper:1o_10b_vs_1r").unwrap_or_else(|e| panic!("{env}: {e:#}"));
        assert_eq!(short.protocol().unwrap().to_string(), want.join("+"));
        short.check().unwrap_or_else(|e| panic!("{env}: {e:#}"));
    }
    // Not a paper spec: unchanged (a directory or files).
    assert_eq!(lmac_run::train::resolve_paper_spec("a.json+b.json", "x:y").unwrap(), "a.json+b.json");
    assert_eq!(lmac_run::train::resolve_paper_spec("papers/x", "x:y").unwrap(), "papers/x");
}

/// The authors' placeholders are reported without a dataset: `lmac protocol check` on their
/// 1o_10b design names phase 2's anchor (constant zeros in their code) and nothing else.
#[test]
fn protocol_check_reports_the_authors_placeholders_as_constant() {
    let dir = paper_designs_dir().expect("protocols/paper").join("smaclite_1o_10b_vs_1r");
    let files: Vec<String> = (0..3).map(|k| dir.join(format!("phase{k}/protocol.json")).display().to_string()).collect();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_lmac"))
        .args(["protocol", "check", "--env", "smaclite:1o_10b_vs_1r"])
        .args(&files)
        .output()
        .expect("running lmac protocol check");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{text}\n{}", String::from_utf8_lossy(&out.stderr));
    let warnings: Vec<&str> = text.lines().filter(|l| l.contains("constant by construction")).collect();
    assert_eq!(warnings.len(), 1, "{text}");
    assert!(warnings[0].contains("phase 2") && warnings[0].contains("`overseer_anchor`") && warnings[0].contains("value 0"), "{text}");

    // `paper`, `paper:<task>` and the design directory name the same phases, as for `lmac train --protocol`.
    let lmac = |args: &[&str]| std::process::Command::new(env!("CARGO_BIN_EXE_lmac")).args(args).output().expect("running lmac");
    let total = |t: &str| t.lines().find(|l| l.starts_with("all phases:")).map(str::to_string);
    for spec in ["paper", "paper:1o_10b_vs_1r", dir.to_str().unwrap()] {
        let out = lmac(&["protocol", "check", "--env", "smaclite:1o_10b_vs_1r", spec]);
        let by_name = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{spec}: {}", String::from_utf8_lossy(&out.stderr));
        assert_eq!(total(&by_name), total(&text), "{spec}: {by_name}");
    }
    let explained = lmac(&["protocol", "explain", "paper:1o_10b_vs_1r"]);
    assert!(explained.status.success() && !explained.stdout.is_empty(), "{}", String::from_utf8_lossy(&explained.stderr));
    let bare = lmac(&["protocol", "explain", "paper"]);
    assert!(
        !bare.status.success() && String::from_utf8_lossy(&bare.stderr).contains("give --env"),
        "{}",
        String::from_utf8_lossy(&bare.stderr)
    );
}
