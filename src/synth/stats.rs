//! `cmr-agent synth stats`: where a world's LiDAR points land (ground, buildings, vegetation,
//! vehicles, people, structures), per world family, so the families can be compared in numbers.

use std::collections::BTreeMap;

use anyhow::Result;

use super::args::WorldArgs;
use super::generate::SequencePlan;
use super::lidar::scan_labelled;
use super::noise::hash;
use super::scene::Class;
use super::worlds::WorldKind;

#[derive(Debug, clap::Args)]
pub struct StatsArgs {
    /// Sequences per world.
    #[arg(long, default_value_t = 3)]
    pub sequences: usize,
    /// Frames scanned per sequence (spread along it).
    #[arg(long, default_value_t = 4)]
    pub frames: usize,
    #[command(flatten)]
    pub world: WorldArgs,
}

/// Points per class over `frames` sweeps of each of `sequences` sequences of `world`.
pub fn class_counts(args: &WorldArgs, world: WorldKind, sequences: usize, frames: usize) -> Result<(BTreeMap<Class, usize>, usize)> {
    let mut counts = BTreeMap::new();
    let config = WorldArgs { world: Some(world), ..args.clone() }.config(sequences, 0, frames * 5);
    config.validate()?;
    let mut sweeps = 0;
    for s in 0..sequences {
        let plan = SequencePlan::new(&config, s)?;
        for f in (0..frames).map(|k| k * 5 + 2) {
            let pose = plan.trajectory.world_from_lidar(f);
            for (_, _, class) in scan_labelled(&plan.scene, &plan.rig.lidar, &pose, hash(&[plan.seed, f as u64])) {
                *counts.entry(class).or_insert(0) += 1;
            }
            sweeps += 1;
        }
    }
    Ok((counts, sweeps))
}

pub fn run(args: &StatsArgs) -> Result<()> {
    let worlds: Vec<WorldKind> = match args.world.world {
        Some(w) => vec![w],
        None => std::iter::once(WorldKind::Classic).chain(super::worlds::DRAWN).collect(),
    };
    print!("| world | points/sweep |");
    for c in Class::ALL {
        print!(" {} |", c.name());
    }
    println!();
    println!("|---|---:|{}", "---:|".repeat(Class::ALL.len()));
    for world in worlds {
        let (counts, sweeps) = class_counts(&args.world, world, args.sequences, args.frames)?;
        let total: usize = counts.values().sum();
        print!("| {} | {:.0} |", world.name(), total as f64 / sweeps.max(1) as f64);
        for c in Class::ALL {
            print!(" {:.1} % |", 100.0 * *counts.get(&c).unwrap_or(&0) as f64 / total.max(1) as f64);
        }
        println!();
    }
    Ok(())
}
