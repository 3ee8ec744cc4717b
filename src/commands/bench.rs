//! `aim bench ...`: benchmarks that print JSON so numbers compare across commits.

#[derive(clap::Subcommand)]
pub enum Bench {
    /// Rasterizer forward and forward+backward timings.
    Render {
        /// Print JSON only.
        #[arg(long)]
        json: bool,
        /// Timed repetitions per case (the median is reported).
        #[arg(long, default_value_t = 7)]
        repeats: usize,
    },
}

pub fn run(b: Bench) -> anyhow::Result<()> {
    match b {
        Bench::Render { json, repeats } => {
            let rows = aim::bench::render_bench(&[256, 512], &[10_000, 50_000, 200_000], repeats.max(1));
            let report = serde_json::json!({
                "bench": "render",
                "threads": rayon::current_num_threads(),
                "rows": rows,
            });
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("{}", serde_json::to_string_pretty(&report)?);
            }
        }
    }
    Ok(())
}
