//! `matflow-bench invert`: wall time against error for the inverse
//! rendering routes, budgets and skips, on the reference scenes.
//!
//! Every configuration runs in a child `matflow invert` process, so that
//! its wall time and peak memory (VmHWM) are its own; the numbers come from
//! the child's `summary.json`.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;
use matflow_inverse::routes::Side;
use matflow_scene::metrics::psnr_gamma;
use matflow_scene::{io, Image};

use matflow_cli::routes::{route_names, route_parser};

#[derive(Args)]
pub struct BenchInvertArgs {
    /// Input bundles (reference layout with gt_image and predictions).
    #[arg(long, num_args = 1.., default_values = ["../shared/data/materialist/indoor", "../shared/data/materialist/jinjya"])]
    pub bundles: Vec<PathBuf>,
    /// Budgets in seconds.
    #[arg(long, num_args = 1.., default_values_t = [5.0, 15.0, 60.0])]
    pub budgets: Vec<f64>,
    /// Material routes. Given with --env-routes, every pair runs. By
    /// default every registered route runs once: each material route with
    /// the default envmap route, each other envmap route with the default
    /// material route.
    #[arg(long, num_args = 1.., value_parser = route_parser(Side::Mat))]
    pub mat_routes: Vec<String>,
    /// Envmap routes (see --mat-routes).
    #[arg(long, num_args = 1.., value_parser = route_parser(Side::Env))]
    pub env_routes: Vec<String>,
    /// Print the configurations and run nothing.
    #[arg(long)]
    pub dry_run: bool,
    /// Also run the skip ablations at the largest budget (default routes):
    /// no table denoising, no exposure ratio, one bounce fewer, no early
    /// stopping.
    #[arg(long)]
    pub skips: bool,
    /// Also re-render each result independently at this many samples per
    /// pixel (`matflow render --bundle OUT --spp N`, fresh random numbers,
    /// no denoising) and report its PSNR against the input: the recovered
    /// scene's error without the final re-render's noise. 0: off.
    #[arg(long, default_value_t = 0)]
    pub rerender_spp: u32,
    /// Where the child runs write their bundles.
    #[arg(long, default_value = "target/bench-invert")]
    pub work: PathBuf,
    /// Relighting on unseen scenes instead: the validation set written by
    /// `crates/bench/scripts/relight_scenes.py` (its folder, with validation.json). Every
    /// budget of --budgets runs on every scene of --halves.
    #[arg(long)]
    pub validation: Option<PathBuf>,
    /// With --validation: which halves (tuning, heldback).
    #[arg(long, num_args = 1.., default_values = ["tuning", "heldback"])]
    pub halves: Vec<String>,
    /// With --validation: a configuration, a string of extra `invert`
    /// flags ("" is the defaults), optionally named as `name=flags`. One
    /// per `--variants`; repeat it for more (a value may start with `-`,
    /// so one flag takes exactly one value and never swallows the
    /// options after it).
    #[arg(long, action = clap::ArgAction::Append, num_args = 1, allow_hyphen_values = true, default_values = [""])]
    pub variants: Vec<String>,
    /// With --validation: only these scenes (e.g. scene-03).
    #[arg(long, num_args = 1..)]
    pub scenes: Vec<String>,
    /// With --validation: samples per pixel of the evaluation renders.
    #[arg(long, default_value_t = 64)]
    pub relight_spp: u32,
    /// With --validation: the geometry past the frame, for `invert` and
    /// every render (`--complete`: auto, none, planes, room, closed);
    /// several run in turn.
    #[arg(long, num_args = 1.., default_values = ["auto"])]
    pub complete: Vec<matflow_nodes::completion::CompleteArg>,
    /// With --validation: only the geometry part (the true maps and light
    /// rendered on each completion against the truths), no inversion.
    #[arg(long)]
    pub geometry_only: bool,
}

/// `name=flags` or just flags (named by themselves; "" is "default").
fn parse_variant(v: &str) -> (String, Vec<String>) {
    let (name, flags) = match v.split_once('=') {
        Some((n, f)) if !n.trim_start().starts_with('-') => (n.trim().to_string(), f),
        _ => (String::new(), v),
    };
    let flags: Vec<String> = flags.split_whitespace().map(String::from).collect();
    let name = if !name.is_empty() {
        name
    } else if flags.is_empty() {
        "default".into()
    } else {
        flags.join(" ")
    };
    (name, flags)
}

struct Row {
    scene: String,
    budget: f64,
    route: String,
    variant: String,
    seconds: f64,
    psnr: f64,
    ssim: f64,
    fit_psnr: f64,
    peak_mb: f64,
    /// PSNR of the independent `--rerender-spp` render (NaN: not run).
    independent: f64,
}

/// PSNR against the input of an independent `spp`-sample render of the
/// recovered bundle `out` (its `matflow render` report's `photo_psnr`).
fn independent_rerender(exe: &Path, out: &Path, spp: u32) -> Result<f64> {
    // Beside the bundle: a render may not write into the folder it reads.
    let name = out.file_name().unwrap_or_default().to_string_lossy();
    let exr = out.with_file_name(format!("{name}-rerender-{spp}spp.exr"));
    let args: Vec<String> = vec![
        "render".into(),
        "--bundle".into(),
        crate::harness::path_arg(out),
        "--spp".into(),
        spp.to_string(),
        "--out".into(),
        crate::harness::path_arg(&exr),
        "--quiet".into(),
    ];
    crate::harness::stage_child(exe, &args, false)
        .with_context(|| format!("matflow render of {}", out.display()))?;
    let p = exr.with_extension("json");
    let text = std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
    let v: serde_json::Value = serde_json::from_slice(&text)?;
    v["photo_psnr"]
        .as_f64()
        .with_context(|| format!("{}: no photo_psnr", p.display()))
}

fn run_one(
    exe: &Path,
    bundle: &Path,
    out: &Path,
    budget: f64,
    route: &str,
    extra: &[String],
) -> Result<(serde_json::Value, crate::harness::StageTiming)> {
    let mut args: Vec<String> = vec![
        "invert".into(),
        "--bundle".into(),
        crate::harness::path_arg(bundle),
        "--out".into(),
        crate::harness::path_arg(out),
        "--budget-seconds".into(),
        budget.to_string(),
        "--mat-route".into(),
        route.into(),
        "--quiet".into(),
    ];
    args.extend(extra.iter().cloned());
    let timing = crate::harness::stage_child(exe, &args, false)
        .with_context(|| format!("matflow invert on {}", bundle.display()))?;
    let p = out.join("summary.json");
    let text = std::fs::read(&p).with_context(|| format!("reading {}", p.display()))?;
    Ok((serde_json::from_slice(&text)?, timing))
}

/// PSNR of the reference's stored re-render against the input. The stored
/// image is linear for some scenes and γ-encoded for others (METHOD.md);
/// the encoding is taken as whichever matches the input better.
fn reference_psnr(bundle: &Path) -> Option<f64> {
    let gt = io::read_exr_rgb(&bundle.join("gt_image.exr")).ok()?;
    let r = io::read_exr_rgb(&bundle.join("best_results/rendered_img.exr")).ok()?;
    if r.width != gt.width || r.height != gt.height {
        return None;
    }
    let lin = psnr_gamma(&r, &gt);
    let decoded = Image::from_vec(
        r.width,
        r.height,
        r.data
            .iter()
            .map(|v| v.max(glam::Vec3::ZERO).powf(2.2))
            .collect(),
    );
    Some(lin.max(psnr_gamma(&decoded, &gt)))
}

pub fn bench_invert(a: BenchInvertArgs) -> Result<()> {
    std::fs::create_dir_all(&a.work)?;
    if let Some(dir) = &a.validation {
        return validation(&a, dir);
    }
    outln!(
        "bench invert: {} thread(s); each row is one child `matflow invert` run; rerender = \
         independent render of the recovered scene vs the input (sRGB γ 2.2)",
        rayon::current_num_threads()
    );
    let exe = if a.dry_run {
        None
    } else {
        Some(crate::harness::matflow_exe()?)
    };
    let mut rows = Vec::new();
    for bundle in &a.bundles {
        let scene = bundle
            .file_name()
            .map(|s| s.to_string_lossy().to_string())
            .unwrap_or_default();
        if let Some(p) = reference_psnr(bundle) {
            outln!("  {scene}: reference's stored result {p:.2} dB");
        }
        for c in configurations(&a) {
            let Some(exe) = &exe else {
                outln!(
                    "  {scene:<8} budget {:>5.0} s  material route {:<8} {:<28} extra flags: {}",
                    c.budget,
                    c.route,
                    c.variant,
                    c.flags.join(" ")
                );
                continue;
            };
            let out = a.work.join(format!(
                "{scene}-{}-{}-{}",
                c.budget,
                c.route,
                c.variant.replace([' ', '(', ')'], "_")
            ));
            let (s, timing) = run_one(exe, bundle, &out, c.budget, &c.route, &c.flags)?;
            let f = |k: &str, m: &str| s[k][m].as_f64().unwrap_or(f64::NAN);
            let independent = if a.rerender_spp > 0 {
                independent_rerender(exe, &out, a.rerender_spp)?
            } else {
                f64::NAN
            };
            let row = Row {
                scene: scene.clone(),
                budget: c.budget,
                route: c.route,
                variant: c.variant,
                seconds: timing.seconds,
                psnr: f("rerender", "psnr"),
                ssim: f("rerender", "ssim"),
                fit_psnr: f("fit", "psnr"),
                peak_mb: timing.peak_bytes / 1e6,
                independent,
            };
            outln!(
                "  {:<8} budget {:>5.0} s  {:<6} {:<28} {:>6.1} s  rerender {:>6.2} dB  SSIM {:.3}  fit {:>6.2} dB  peak {:>5.0} MB",
                row.scene, row.budget, row.route, row.variant, row.seconds, row.psnr, row.ssim,
                row.fit_psnr, row.peak_mb
            );
            if a.rerender_spp > 0 {
                outln!(
                    "           independent {}-spp re-render {:>6.2} dB",
                    a.rerender_spp,
                    row.independent
                );
            }
            rows.push(row);
        }
    }
    if exe.is_some() {
        print_table(&rows, a.rerender_spp);
    }
    Ok(())
}

/// `--validation DIR`: relighting on the validation scenes, per budget.
fn validation(a: &BenchInvertArgs, dir: &Path) -> Result<()> {
    let exe = crate::harness::matflow_exe()?;
    let v = crate::suites::relight::load_validation(dir)?;
    // The geometry part renders the truths alone: one budget is all.
    let budgets = if a.geometry_only {
        &a.budgets[..a.budgets.len().min(1)]
    } else {
        &a.budgets[..]
    };
    for &budget in budgets {
        crate::suites::relight::bench_relight(
            &v,
            &crate::suites::relight::RelightRun {
                exe: &exe,
                budget,
                variants: a.variants.iter().map(|x| parse_variant(x)).collect(),
                spp: a.relight_spp,
                complete: a.complete.clone(),
                geometry_only: a.geometry_only,
                halves: a.halves.clone(),
                only: a.scenes.clone(),
                work: &a.work,
            },
        )?;
    }
    Ok(())
}

/// One child run of `bench invert`: a budget, a material route, what the
/// row is called and the flags that make it so.
struct Config {
    budget: f64,
    route: String,
    variant: String,
    flags: Vec<String>,
}

/// The (envmap route, material route) pairs to run: by default every
/// material route under the first envmap route, then every other envmap
/// route under the first material route (the registry's own lists, so a
/// new route is benchmarked without being named here).
fn route_pairs(a: &BenchInvertArgs) -> Vec<(String, String)> {
    let default_env = route_names(Side::Env)[0];
    let default_mat = route_names(Side::Mat)[0];
    let own = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    if a.env_routes.is_empty() && a.mat_routes.is_empty() {
        let mut v: Vec<(String, String)> = route_names(Side::Mat)
            .into_iter()
            .map(|m| (default_env.to_string(), m.to_string()))
            .collect();
        v.extend(
            route_names(Side::Env)
                .into_iter()
                .skip(1)
                .map(|e| (e.to_string(), default_mat.to_string())),
        );
        return v;
    }
    let envs = if a.env_routes.is_empty() {
        own(&[default_env])
    } else {
        a.env_routes.clone()
    };
    let mats = if a.mat_routes.is_empty() {
        own(&[default_mat])
    } else {
        a.mat_routes.clone()
    };
    envs.iter()
        .flat_map(|e| mats.iter().map(move |m| (e.clone(), m.clone())))
        .collect()
}

/// Every run for one bundle: each budget × route pair, then (with
/// `--skips`) the default at the largest budget with one step skipped.
fn configurations(a: &BenchInvertArgs) -> Vec<Config> {
    let default_env = route_names(Side::Env)[0];
    let default_mat = route_names(Side::Mat)[0];
    let max_budget = a.budgets.iter().cloned().fold(f64::NAN, f64::max);
    let pairs = route_pairs(a);
    let mut configs = Vec::new();
    for &budget in &a.budgets {
        for (env, mat) in &pairs {
            configs.push(Config {
                budget,
                route: mat.clone(),
                variant: if env == default_env {
                    "default".to_string()
                } else {
                    format!("envmap {env}")
                },
                flags: vec!["--env-route".into(), env.clone()],
            });
        }
    }
    if a.skips {
        for (name, flags) in [
            ("no table denoising", &["--denoise", "0"][..]),
            ("no exposure ratio", &["--no-rescale"]),
            ("depth 3 (one bounce fewer)", &["--depth", "3"]),
            ("no early stopping", &["--no-early-stop"]),
        ] {
            configs.push(Config {
                budget: max_budget,
                route: default_mat.into(),
                variant: name.into(),
                flags: flags.iter().map(|f| f.to_string()).collect(),
            });
        }
    }
    configs
}

fn print_table(rows: &[Row], rerender_spp: u32) {
    let (head, rule) = if rerender_spp > 0 {
        (
            format!(" independent {rerender_spp}-spp re-render (dB) |"),
            "---|",
        )
    } else {
        (String::new(), "")
    };
    outln!();
    outln!("| scene | budget (s) | material route | variant | wall (s) | rerender PSNR (dB) | SSIM | fit PSNR (dB) | peak memory (MB) |{head}");
    outln!("|---|---|---|---|---|---|---|---|---|{rule}");
    for r in rows {
        let extra = if rerender_spp > 0 {
            format!(" {:.2} |", r.independent)
        } else {
            String::new()
        };
        outln!(
            "| {} | {:.0} | {} | {} | {:.1} | {:.2} | {:.3} | {:.2} | {:.0} |{extra}",
            r.scene,
            r.budget,
            r.route,
            r.variant,
            r.seconds,
            r.psnr,
            r.ssim,
            r.fit_psnr,
            r.peak_mb
        );
    }
}

#[cfg(test)]
mod tests {
    use super::parse_variant;

    #[test]
    fn variants_are_named_flags() {
        assert_eq!(parse_variant(""), ("default".into(), vec![]));
        assert_eq!(
            parse_variant("--delta 0.5"),
            ("--delta 0.5".into(), vec!["--delta".into(), "0.5".into()])
        );
        assert_eq!(
            parse_variant("strong prior=--delta 0.5"),
            ("strong prior".into(), vec!["--delta".into(), "0.5".into()])
        );
    }

    /// `--variants` takes one value each time, so the options after it
    /// are the bench's own (it once swallowed `--relight-spp 16` as
    /// variants).
    #[test]
    fn a_variant_takes_one_value_and_leaves_the_options_after_it() {
        use clap::Parser;
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            a: super::BenchInvertArgs,
        }
        let c = Cli::try_parse_from([
            "bench",
            "--validation",
            "v",
            "--variants",
            "",
            "--variants",
            "off=--light-guide off",
            "--relight-spp",
            "16",
        ])
        .unwrap();
        assert_eq!(c.a.variants, ["", "off=--light-guide off"]);
        assert_eq!(c.a.relight_spp, 16);
        let c = Cli::try_parse_from(["bench", "--validation", "v"]).unwrap();
        assert_eq!(c.a.variants, [""]);
    }

    /// Every registered route is benchmarked by default, each envmap
    /// route by name (`--env-route NAME`) and each material route as a
    /// row of its own: the registry is the only list of routes.
    #[test]
    fn every_registered_route_is_benchmarked_by_default() {
        use clap::Parser;
        use matflow_inverse::routes::{ENV_ROUTES, MAT_ROUTES};
        #[derive(Parser)]
        struct Cli {
            #[command(flatten)]
            a: super::BenchInvertArgs,
        }
        let c = Cli::try_parse_from(["bench", "--budgets", "5", "10"]).unwrap();
        let configs = super::configurations(&c.a);
        for e in ENV_ROUTES {
            assert!(
                configs
                    .iter()
                    .any(|c| c.flags == ["--env-route", e.name] && c.budget == 10.0),
                "envmap route {} not benchmarked",
                e.name
            );
        }
        for m in MAT_ROUTES {
            assert!(
                configs.iter().any(|c| c.route == m.name && c.budget == 5.0),
                "material route {} not benchmarked",
                m.name
            );
        }
    }
}
