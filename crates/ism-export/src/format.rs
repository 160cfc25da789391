//! Output formats, chosen from a file name, and one entry point writing a [`Mesh`] to any of them.

use std::io::Write;
use std::path::Path;

use crate::gltf::{write_gltf, GltfContainer};
use crate::mesh::Mesh;
use crate::obj::write_obj;
use crate::vtk::{UnstructuredGrid, VtuCompression};
use crate::Result;

/// A mesh output format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ExportFormat {
    /// Wavefront OBJ (`.obj`).
    Obj,
    /// glTF 2.0 JSON with embedded buffer (`.gltf`).
    Gltf,
    /// Binary glTF 2.0 (`.glb`).
    Glb,
    /// Legacy VTK, ASCII (`.vtk`).
    VtkLegacy,
    /// VTK XML unstructured grid (`.vtu`).
    Vtu,
}

impl ExportFormat {
    /// Every format.
    pub const ALL: [ExportFormat; 5] = [
        ExportFormat::Obj,
        ExportFormat::Gltf,
        ExportFormat::Glb,
        ExportFormat::VtkLegacy,
        ExportFormat::Vtu,
    ];

    /// The format of a file name's extension (case-insensitive), if known.
    pub fn from_path(path: &Path) -> Option<ExportFormat> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        Some(match ext.as_str() {
            "obj" => ExportFormat::Obj,
            "gltf" => ExportFormat::Gltf,
            "glb" => ExportFormat::Glb,
            "vtk" => ExportFormat::VtkLegacy,
            "vtu" => ExportFormat::Vtu,
            _ => return None,
        })
    }

    /// The usual extension, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            ExportFormat::Obj => "obj",
            ExportFormat::Gltf => "gltf",
            ExportFormat::Glb => "glb",
            ExportFormat::VtkLegacy => "vtk",
            ExportFormat::Vtu => "vtu",
        }
    }

    /// Whether the format can carry the complex itself ([`crate::volume`]).
    pub fn supports_volume(self) -> bool {
        matches!(self, ExportFormat::VtkLegacy | ExportFormat::Vtu)
    }
}

/// Writes `mesh` in `format`, streaming to `out`. `name` labels the object where the format has
/// a place for it.
///
/// # Errors
/// Whatever the format's writer reports ([`crate::Error::Io`], [`crate::Error::TooLarge`],
/// [`crate::Error::Gltf`]).
pub fn write_mesh<W: Write>(
    mesh: &Mesh,
    format: ExportFormat,
    name: Option<&str>,
    out: W,
) -> Result<()> {
    write_mesh_with(mesh, format, name, VtuCompression::None, out)
}

/// [`write_mesh`], a `.vtu`'s arrays stored as `compression` says
/// ([`UnstructuredGrid::write_vtu_with`]; the other formats ignore it).
///
/// # Errors
/// As [`write_mesh`].
pub fn write_mesh_with<W: Write>(
    mesh: &Mesh,
    format: ExportFormat,
    name: Option<&str>,
    compression: VtuCompression,
    out: W,
) -> Result<()> {
    match format {
        ExportFormat::Obj => write_obj(mesh, name, out),
        ExportFormat::Gltf => write_gltf(mesh, name, GltfContainer::Text, out),
        ExportFormat::Glb => write_gltf(mesh, name, GltfContainer::Binary, out),
        ExportFormat::VtkLegacy => {
            UnstructuredGrid::from_mesh(mesh).write_legacy(name.unwrap_or("ISM export"), out)
        }
        ExportFormat::Vtu => UnstructuredGrid::from_mesh(mesh).write_vtu_with(out, compression),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_round_trip_through_their_extensions() {
        for f in ExportFormat::ALL {
            let name = format!("shape.{}", f.extension().to_uppercase());
            assert_eq!(ExportFormat::from_path(Path::new(&name)), Some(f));
        }
        assert_eq!(ExportFormat::from_path(Path::new("shape.stl")), None);
        assert_eq!(ExportFormat::from_path(Path::new("shape")), None);
    }
}
