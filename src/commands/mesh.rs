//! `aim mesh SPLATS.ply --out MESH.obj [--compare GT.obj ...]`: a Gaussian set's
//! surface by TSDF fusion (OBJ and PLY), optionally compared with reference meshes.

use std::path::PathBuf;

use aim::eval::shape::chamfer_meshes_sampled;
use aim::mesh::tsdf::{mesh_gaussians, object_size, TsdfConfig};
use aim::mesh::{read_obj, MeshData};

#[derive(clap::Args)]
pub struct Args {
    /// A 3DGS PLY (original layout).
    pub splats: PathBuf,
    /// Output mesh: OUT.obj and OUT.ply beside it.
    #[arg(long)]
    pub out: PathBuf,
    /// Reference OBJ meshes (merged) to report the Chamfer distance to.
    #[arg(long, num_args = 1..)]
    pub compare: Vec<PathBuf>,
    /// Samples per mesh for the Chamfer distance (the paper's 10k by default; more
    /// lowers the sampling's own share of it).
    #[arg(long, default_value_t = aim::eval::shape::CHAMFER_SAMPLES)]
    pub samples: usize,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let gs = aim::splat::ply::read_ply(&args.splats)?;
    let cfg = TsdfConfig::default();
    let size = object_size([&gs], cfg.min_opacity)
        .ok_or_else(|| anyhow::anyhow!("{}: no Gaussian with opacity >= {}", args.splats.display(), cfg.min_opacity))?;
    let start = std::time::Instant::now();
    let mesh = mesh_gaussians(&gs, size, &cfg)?;
    mesh.write_obj_and_ply(&args.out, &format!("aim mesh of {}", args.splats.display()))?;
    println!(
        "{} vertices, {} triangles, area {:.4} m^2 in {:.1} s -> {} (and .ply)",
        mesh.vertices.len(),
        mesh.triangles.len(),
        mesh.area(),
        start.elapsed().as_secs_f64(),
        args.out.with_extension("obj").display()
    );
    if !args.compare.is_empty() {
        let refs = args.compare.iter().map(|p| read_obj(p)).collect::<Result<Vec<_>, _>>()?;
        let reference = MeshData::merged(&refs);
        let cd = chamfer_meshes_sampled(&mesh, &reference, 0, args.samples)
            .ok_or_else(|| anyhow::anyhow!("the reference meshes are empty"))?;
        // The floor: the reference against itself, sampled twice.
        let floor = chamfer_meshes_sampled(&reference, &reference, 1, args.samples).map_or(0.0, |c| c.l2_mm);
        println!(
            "Chamfer distance to the reference ({} samples each): {:.3} mm (squared x1000: {:.5}); the reference against itself: {floor:.3} mm",
            args.samples, cd.l2_mm, cd.squared_l2_x1000
        );
    }
    Ok(())
}
