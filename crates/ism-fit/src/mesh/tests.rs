//! Tests of the mesh module (a child of [`super`], the distance, for its private state): the
//! readers (through [`TriangleMesh`]'s loaders), winding numbers, signed distances and
//! enclosures, against brute force and closed forms.

use std::path::Path;

use ism_format::io::Limits;

use super::super::*;
use super::*;

/// A cube `[-s, s]³` as 12 outward triangles, with the 8 corners shifted by `offset`.
/// The error's text with its causes, as the CLI and the Python package print it.
fn error_text(err: &FitError) -> String {
    ism_format::ErrorChain(err).to_string()
}

fn cube(s: f64, offset: P3) -> TriangleMesh {
    let mut positions = Vec::new();
    for i in 0..8 {
        let c = [i & 1, (i >> 1) & 1, (i >> 2) & 1].map(|b| if b == 1 { s } else { -s });
        positions.push([c[0] + offset[0], c[1] + offset[1], c[2] + offset[2]]);
    }
    let quads = [
        [0, 2, 3, 1], // z = -s
        [4, 5, 7, 6], // z = +s
        [0, 1, 5, 4], // y = -s
        [2, 6, 7, 3], // y = +s
        [0, 4, 6, 2], // x = -s
        [1, 3, 7, 5], // x = +s
    ];
    let triangles = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    TriangleMesh {
        positions,
        triangles,
    }
}

fn icosphere(level: usize) -> TriangleMesh {
    TriangleMesh::icosphere(level, 1.0, [0.0; 3])
}

/// [`TriangleMesh::torus`]: saddle vertices and concave edges on its inner side.
fn torus_mesh(n: u32, m: u32, big: f64, small: f64) -> TriangleMesh {
    TriangleMesh::torus(n, m, big, small)
}

/// The pseudonormal sign agrees with the brute-force winding number (an independent sum of
/// all solid angles) on nonconvex closed meshes — a torus (saddle corners, concave edges) and
/// an icosphere with radial bumps — at random points in the box and at points just off the
/// surface near corners, edges and faces; and it is the fast path for most of them.
#[test]
fn pseudonormal_sign_agrees_with_the_winding_number() {
    let mut bumpy = TriangleMesh::icosphere(3, 1.0, [0.0; 3]);
    for (k, p) in bumpy.positions.iter_mut().enumerate() {
        let f = 1.0 + 0.25 * ((k * 7919) % 13) as f64 / 13.0;
        *p = p.map(|x| x * f);
    }
    for (name, mesh) in [("torus", torus_mesh(24, 12, 1.0, 0.35)), ("bumpy", bumpy)] {
        let g = MeshDistance::new(mesh).unwrap();
        assert!(g.check().is_closed_manifold(), "{name}");
        assert!(g.pseudonormals.is_some(), "{name}");
        let mut queries = points(3000, -1.6, 1.6, 11);
        // Just off the surface: from each vertex and from edge midpoints and face centres,
        // along a deterministic direction, at distances from 1e-12 to 1e-1.
        let dirs = points(4 * g.mesh.triangles.len(), -1.0, 1.0, 29);
        for (k, t) in g.mesh.triangles.iter().enumerate() {
            let v = t.map(|i| g.mesh.positions[i as usize]);
            let sites = [
                v[0],
                [0, 1, 2].map(|x| 0.5 * (v[0][x] + v[1][x])),
                [0, 1, 2].map(|x| (v[0][x] + v[1][x] + v[2][x]) / 3.0),
                v[1],
            ];
            for (j, site) in sites.into_iter().enumerate() {
                let h = 10f64.powi(-1 - ((k + j) % 12) as i32);
                queries.push(axpy(site, h, dirs[4 * k + j]));
            }
        }
        let mut fast = 0;
        for p in &queries {
            let (_, t) = g.closest_point(*p);
            let truth = g.winding_number_brute_force(*p) > 0.5;
            assert_eq!(g.side(*p, t), truth, "{name} at {p:?}");
            if let Some(side) = g.pseudonormal_side(*p, t) {
                assert_eq!(side, truth, "{name} at {p:?}");
                fast += 1;
            }
        }
        // Every point but those within ~1e-12 of the surface (1 in 12 of the near ones).
        assert!(
            fast * 10 > queries.len() * 9,
            "{name}: {fast} of {}",
            queries.len()
        );
    }
}

/// Deterministic points in a box (a fixed LCG: the tests need no RNG crate for this).
fn points(n: usize, lo: f64, hi: f64, seed: u64) -> Vec<P3> {
    let mut rng = crate::test_rng::Lcg::new(seed);
    let mut next = move || lo + (hi - lo) * rng.unit();
    (0..n).map(|_| [next(), next(), next()]).collect()
}

/// Independent point–triangle distance: projection onto the plane when it falls inside
/// (barycentric test), otherwise the nearest of the three edges as segments.
fn brute_distance(p: P3, [a, b, c]: [P3; 3]) -> f64 {
    let n = cross(sub(b, a), sub(c, a));
    let nn = dot(n, n);
    let h = dot(sub(p, a), n) / nn;
    let q = axpy(p, -h, n);
    let inside = [(a, b), (b, c), (c, a)]
        .iter()
        .all(|&(u, v)| dot(cross(sub(v, u), sub(q, u)), n) >= 0.0);
    if inside {
        return norm(sub(p, q));
    }
    [(a, b), (b, c), (c, a)]
        .iter()
        .map(|&(u, v)| {
            let d = sub(v, u);
            let t = (dot(sub(p, u), d) / dot(d, d)).clamp(0.0, 1.0);
            norm(sub(p, axpy(u, t, d)))
        })
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn winding_number_is_one_inside_and_zero_outside() {
    for mesh in [cube(0.5, [0.1, -0.2, 0.05]), icosphere(2)] {
        let d = MeshDistance::new(mesh).unwrap();
        assert!(!d.flipped());
        for p in points(400, -1.5, 1.5, 7) {
            let w = d.winding_number(p);
            let brute = d.winding_number_brute_force(p);
            assert!((w - brute).abs() < 1e-9, "{p:?}: {w} vs {brute}");
            let (q, _) = d.closest_point(p);
            if norm(sub(p, q)) < 1e-9 {
                continue;
            }
            assert!(
                w.abs() < 1e-9 || (w - 1.0).abs() < 1e-9,
                "{p:?}: w = {w} is not 0 or 1"
            );
        }
    }
    // Against ground truth that does not use solid angles: the cube's own inequalities.
    let d = MeshDistance::new(cube(0.5, [0.0; 3])).unwrap();
    for p in points(300, -1.0, 1.0, 3) {
        let inside = p.iter().all(|x| x.abs() < 0.5);
        assert_eq!(d.is_inside(p), inside, "{p:?}");
        assert_eq!(d.value(&p) < 0.0, inside, "{p:?}");
    }
}

#[test]
fn hierarchy_matches_ground_truth_on_a_larger_mesh() {
    let d = MeshDistance::new(icosphere(4)).unwrap();
    assert_eq!(d.check().triangles, 5120);
    for p in points(200, -1.3, 1.3, 11) {
        let w = d.winding_number(p);
        let expect = if norm(p) < 0.99 {
            1.0
        } else if norm(p) > 1.0 {
            0.0
        } else {
            continue;
        };
        assert!((w - expect).abs() < 1e-9, "{p:?}: {w}");
    }
}

#[test]
fn signed_distance_matches_brute_force() {
    for mesh in [cube(0.5, [0.0; 3]), icosphere(2)] {
        let d = MeshDistance::new(mesh.clone()).unwrap();
        for p in points(500, -1.4, 1.4, 5) {
            let brute = mesh
                .triangles
                .iter()
                .map(|t| brute_distance(p, t.map(|v| mesh.positions[v as usize])))
                .fold(f64::INFINITY, f64::min);
            let mut grad = [0.0; 3];
            let g = d.gradient(&p, &mut grad);
            assert!((g.abs() - brute).abs() < 1e-12, "{p:?}: {g} vs {brute}");
            assert!((norm(grad) - 1.0).abs() < 1e-12);
            // The per-thread cache (sign reuse, search hint) answers like a cold query: a
            // tiny and a larger step from p, against the brute-force sign and distance.
            for step in [1e-9, 1e-3, 0.05] {
                let r = axpy(p, step, [0.6, -0.48, 0.64]);
                let brute_r = mesh
                    .triangles
                    .iter()
                    .map(|t| brute_distance(r, t.map(|v| mesh.positions[v as usize])))
                    .fold(f64::INFINITY, f64::min);
                let inside = d.winding_number_brute_force(r) > 0.5;
                let v = d.value(&r);
                assert!((v.abs() - brute_r).abs() < 1e-12, "{r:?}: {v} vs {brute_r}");
                assert!(brute_r < 1e-12 || (v < 0.0) == inside, "{r:?}: {v}");
            }
            // The gradient is that of a distance: stepping along it changes g by the step.
            let h = 1e-7 * brute;
            let ahead = d.value(&axpy(p, h, grad));
            assert!((ahead - g - h).abs() < 1e-3 * h, "{p:?}");
        }
    }
}

#[test]
fn sharp_edges_are_measured() {
    let cube = MeshDistance::new(cube(0.5, [0.0; 3])).unwrap();
    assert!((cube.sharpest_edge() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    assert!(cube.sharpest_edge() > PV_SHARPEST_EDGE);
    // Icosphere level 2: neighbouring normals turn by about 10°.
    let ico = MeshDistance::new(icosphere(2)).unwrap();
    assert!(
        ico.sharpest_edge() < 15f64.to_radians(),
        "{}",
        ico.sharpest_edge()
    );
}

#[test]
fn inverted_mesh_is_flipped_and_topology_is_counted() {
    let mut m = icosphere(1);
    for t in &mut m.triangles {
        t.swap(0, 1);
    }
    let d = MeshDistance::new(m).unwrap();
    assert!(d.flipped());
    assert!(d.value(&[0.0, 0.0, 0.0]) < 0.0);
    let c = d.check();
    assert!(c.is_closed_manifold(), "{c:?}");
    assert_eq!((c.components, c.euler), (1, 2));
    // Two disjoint cubes: 2 components, χ = 4; dropping a triangle opens the mesh.
    let a = cube(0.3, [-0.5, 0.0, 0.0]);
    let b = cube(0.3, [0.5, 0.0, 0.0]);
    let mut two = a.clone();
    two.positions.extend(&b.positions);
    two.triangles
        .extend(b.triangles.iter().map(|t| t.map(|v| v + 8)));
    let c = two.check();
    assert_eq!((c.components, c.euler), (2, 4));
    two.triangles.pop();
    let c = two.check();
    assert_eq!(c.boundary_edges, 3);
    assert!(!c.is_closed_manifold());
}

fn obj_text(mesh: &TriangleMesh) -> String {
    let mut s = String::from("# test\no shape\n");
    for p in &mesh.positions {
        s += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    for t in &mesh.triangles {
        s += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    s
}

/// A GLB holding `mesh` in two halves: node 0 with the first half as-is, node 1 with the
/// second half translated by −`shift` in the buffer and +`shift` by a node translation under
/// a parent with a uniform scale 2 whose child scales by ½ (the transforms must compose).
fn glb_bytes(mesh: &TriangleMesh, shift: [f32; 3]) -> Vec<u8> {
    let half = mesh.triangles.len() / 2;
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    for (part, range) in [(0usize, 0..half), (1, half..mesh.triangles.len())] {
        let tris = &mesh.triangles[range];
        let pos: Vec<[f32; 3]> = tris
            .iter()
            .flat_map(|t| t.iter())
            .map(|&v| {
                let p = mesh.positions[v as usize];
                let s = if part == 1 { shift } else { [0.0; 3] };
                [0, 1, 2].map(|k| p[k] as f32 - s[k])
            })
            .collect();
        let offset = bin.len();
        for p in &pos {
            for x in p {
                bin.extend(x.to_le_bytes());
            }
        }
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for p in &pos {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        views.push(format!(
            r#"{{"buffer":0,"byteOffset":{offset},"byteLength":{}}}"#,
            pos.len() * 12
        ));
        accessors.push(format!(
            r#"{{"bufferView":{part},"componentType":5126,"count":{},"type":"VEC3","min":{lo:?},"max":{hi:?}}}"#,
            pos.len()
        ));
    }
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0,2]}}],
        "nodes":[{{"mesh":0}},{{"mesh":1,"translation":[{},{},{}],"scale":[0.5,0.5,0.5]}},{{"children":[1],"scale":[2,2,2]}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}}}}]}},{{"primitives":[{{"attributes":{{"POSITION":1}}}}]}}],
        "buffers":[{{"byteLength":{}}}],"bufferViews":[{}],"accessors":[{}]}}"#,
        shift[0] / 2.0,
        shift[1] / 2.0,
        shift[2] / 2.0,
        bin.len(),
        views.join(","),
        accessors.join(",")
    );
    glb_container(json, bin)
}

/// A GLB file (glTF 2.0 binary container): the JSON chunk and the BIN chunk, each padded to 4.
fn glb_container(json: String, mut bin: Vec<u8>) -> Vec<u8> {
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    while bin.len() % 4 != 0 {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::new();
    out.extend(b"glTF");
    out.extend(2u32.to_le_bytes());
    out.extend((total as u32).to_le_bytes());
    out.extend((json.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&json);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(&bin);
    out
}

/// A tetrahedron as a GLB whose indices accessor has the given component type and type.
fn indexed_glb(component: u32, kind: &str) -> Vec<u8> {
    let pos: [[f32; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 1.0, 0.0],
        [0.0, 0.0, 1.0],
    ];
    let idx: [u32; 12] = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];
    let mut bin: Vec<u8> = pos.iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
    let ioff = bin.len();
    // Four bytes per index whatever the declared type: enough bytes for every case.
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    let json = format!(
        r#"{{"asset":{{"version":"2.0"}},"scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{{"mesh":0}}],
        "meshes":[{{"primitives":[{{"attributes":{{"POSITION":0}},"indices":1}}]}}],
        "buffers":[{{"byteLength":{}}}],
        "bufferViews":[{{"buffer":0,"byteOffset":0,"byteLength":48}},{{"buffer":0,"byteOffset":{ioff},"byteLength":48}}],
        "accessors":[{{"bufferView":0,"componentType":5126,"count":4,"type":"VEC3","min":[0,0,0],"max":[1,1,1]}},
        {{"bufferView":1,"componentType":{component},"count":12,"type":"{kind}"}}]}}"#,
        bin.len()
    );
    glb_container(json, bin)
}

/// glTF 2.0 allows only unsigned byte/short/int scalar indices; anything else is an error
/// naming the accessor, not a panic (the `gltf` crate's reader has `unreachable!` there; found
/// by the `fit_mesh` fuzz target).
#[test]
fn gltf_indices_of_a_type_the_spec_forbids_are_an_error() {
    let ok = TriangleMesh::from_gltf(&indexed_glb(5125, "SCALAR"), Path::new("t.glb")).unwrap();
    assert_eq!(ok.triangles.len(), 4);
    for (component, kind) in [
        (5120, "SCALAR"),
        (5122, "SCALAR"),
        (5126, "SCALAR"),
        (5125, "VEC2"),
    ] {
        let err = TriangleMesh::from_gltf(&indexed_glb(component, kind), Path::new("t.glb"))
            .map(|m| m.triangles.len());
        let message = error_text(&err.expect_err("forbidden index type accepted"));
        assert!(
            message.contains("indices accessor 1"),
            "{component} {kind}: {message}"
        );
    }
}

/// The tetrahedron of [`indexed_glb`] (u32 indices) under the given `"scene"`/`"scenes"`/
/// `"nodes"` members.
fn tetra_glb(scenes_and_nodes: &str) -> Vec<u8> {
    let glb = indexed_glb(5125, "SCALAR");
    let json_len = u32::from_le_bytes(glb[12..16].try_into().unwrap()) as usize;
    let json = std::str::from_utf8(&glb[20..20 + json_len]).unwrap();
    let bin = glb[20 + json_len + 8..].to_vec();
    let json = json.replacen(
        r#""scene":0,"scenes":[{"nodes":[0]}],"nodes":[{"mesh":0}],"#,
        scenes_and_nodes,
        1,
    );
    assert!(json.contains(scenes_and_nodes), "the template changed");
    glb_container(json, bin)
}

/// A node reached twice in one scene (two parents, or one child listed twice) is refused: 40
/// levels of `children: [next, next]` would instance the mesh 2⁴⁰ times from a few hundred
/// bytes (before, `ism fit --mesh` on such a file was still running when a 20 s timeout stopped it). Scenes may share nodes: a
/// node loaded by an earlier scene is not loaded again. Truth: the triangle counts the files
/// were built with.
#[test]
fn gltf_nodes_are_instanced_once() {
    let chain: Vec<String> = (0..40)
        .map(|i| format!(r#"{{"children":[{},{}]}}"#, i + 1, i + 1))
        .chain([r#"{"mesh":0}"#.to_string()])
        .collect();
    let dag = tetra_glb(&format!(
        r#""scene":0,"scenes":[{{"nodes":[0]}}],"nodes":[{}],"#,
        chain.join(",")
    ));
    let err = TriangleMesh::from_gltf(&dag, Path::new("dag.glb"))
        .map(|m| m.triangles.len())
        .expect_err("a node with two parents accepted");
    assert!(
        error_text(&err).contains("reached twice in scene 0"),
        "{err}"
    );
    // Two parents of one mesh node, no repetition within a children list.
    let two_parents = tetra_glb(
        r#""scene":0,"scenes":[{"nodes":[0,1]}],"nodes":[{"children":[2]},{"children":[2]},{"mesh":0}],"#,
    );
    let err = TriangleMesh::from_gltf(&two_parents, Path::new("t.glb"))
        .map(|m| m.triangles.len())
        .expect_err("a node with two parents accepted");
    assert!(
        error_text(&err).contains("node 2 is reached twice"),
        "{err}"
    );
    // Two scenes sharing the mesh node, none the default: every scene is read, the node once.
    let shared = tetra_glb(r#""scenes":[{"nodes":[0]},{"nodes":[0]}],"nodes":[{"mesh":0}],"#);
    let mesh = TriangleMesh::from_gltf(&shared, Path::new("t.glb")).unwrap();
    assert_eq!(mesh.triangles.len(), 4);
    // Two nodes instancing one mesh is legal and gives both copies.
    let two = tetra_glb(
        r#""scene":0,"scenes":[{"nodes":[0,1]}],"nodes":[{"mesh":0},{"mesh":0,"translation":[5,0,0]}],"#,
    );
    let mesh = TriangleMesh::from_gltf(&two, Path::new("t.glb")).unwrap();
    assert_eq!(mesh.triangles.len(), 8);
}

/// `Limits` bound a mesh read: vertices and triangles (OBJ after parsing, glTF per primitive
/// before it is added) and the file's or buffers' bytes before reading. At the limit the
/// tetrahedron (4 vertices, 4 triangles) reads; one below, it is refused naming the limit.
#[test]
fn limits_refuse_larger_meshes() {
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";
    let glb = indexed_glb(5125, "SCALAR");
    let at = Limits {
        max_vertices: 4,
        max_simplices: 4,
        ..Limits::default()
    };
    let read = |bytes: &[u8], glb: bool, limits: &Limits| {
        if glb {
            TriangleMesh::from_gltf_with_limits(bytes, Path::new("t.glb"), limits)
        } else {
            TriangleMesh::from_obj_with_limits(bytes, Path::new("t.obj"), limits)
        }
        .map(|m| m.triangles.len())
    };
    for (bytes, is_glb) in [(&obj[..], false), (&glb[..], true)] {
        assert_eq!(read(bytes, is_glb, &at).unwrap(), 4);
        for (limits, name) in [
            (
                Limits {
                    max_vertices: 3,
                    ..at
                },
                "max_vertices",
            ),
            (
                Limits {
                    max_simplices: 3,
                    ..at
                },
                "max_simplices",
            ),
        ] {
            let err = read(bytes, is_glb, &limits).expect_err("over the limit");
            assert!(error_text(&err).contains(name), "{name}: {err}");
        }
    }
    // The GLB's one buffer declares 96 bytes.
    let err = read(
        &glb,
        true,
        &Limits {
            max_payload_bytes: 95,
            ..at
        },
    )
    .expect_err("buffers over the limit");
    assert!(error_text(&err).contains("max_payload_bytes"), "{err}");
    // Declared lengths whose sum overflows u64 are over the limit, not a panic.
    let huge = format!(
        r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":{m},"uri":"a.bin"}},{{"byteLength":{m},"uri":"b.bin"}}]}}"#,
        m = u64::MAX - 1
    );
    let err = read(huge.as_bytes(), true, &at).expect_err("overflowing buffers accepted");
    assert!(error_text(&err).contains("max_payload_bytes"), "{err}");
    // A file: its size is checked before it is read.
    let dir = std::env::temp_dir().join(format!("ism-fit-limits-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("t.obj");
    std::fs::write(&path, obj).unwrap();
    let size = obj.len() as u64;
    let load = |max_payload_bytes| {
        TriangleMesh::load_with_limits(
            &path,
            &Limits {
                max_payload_bytes,
                ..Limits::default()
            },
        )
        .map(|m| m.triangles.len())
    };
    assert_eq!(load(size).unwrap(), 4);
    let err = load(size - 1).expect_err("file over the limit");
    assert!(error_text(&err).contains("max_payload_bytes"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A relative buffer URI whose percent-decoding is not UTF-8 is an error, not a panic in the
/// `gltf` crate's importer (found by the `fit_mesh` fuzz target); a valid one still reaches
/// the file system.
#[test]
fn gltf_buffer_uris_that_do_not_decode_are_an_error() {
    let gltf = |uri: &str| {
        format!(r#"{{"asset":{{"version":"2.0"}},"buffers":[{{"byteLength":4,"uri":"{uri}"}}]}}"#)
    };
    let err = TriangleMesh::from_gltf(
        gltf("a%ACb.bin").as_bytes(),
        Path::new("/nonexistent/t.gltf"),
    )
    .map(|m| m.triangles.len())
    .expect_err("undecodable URI accepted");
    assert!(error_text(&err).contains("not UTF-8"), "{err}");
    let err = TriangleMesh::from_gltf(
        gltf("missing%20file.bin").as_bytes(),
        Path::new("/nonexistent/t.gltf"),
    )
    .map(|m| m.triangles.len())
    .expect_err("a missing buffer file accepted");
    assert!(error_text(&err).contains("buffers"), "{err}");
}

#[test]
fn obj_and_glb_of_the_same_shape_give_the_same_function() {
    // Coordinates on a 2⁻¹² grid: exact in f32 and under the test's shifts and scalings, so
    // both formats carry the same numbers and the GLB's halves weld at their seam.
    let mut mesh = icosphere(1);
    for p in &mut mesh.positions {
        *p = p.map(|x| (x * 4096.0).round() / 4096.0);
    }
    let obj = TriangleMesh::from_obj(obj_text(&mesh).as_bytes(), Path::new("s.obj")).unwrap();
    let glb =
        TriangleMesh::from_gltf(&glb_bytes(&mesh, [0.25, -0.5, 1.0]), Path::new("s.glb")).unwrap();
    assert_eq!(obj.check(), glb.check());
    assert_eq!(obj.check().euler, 2);
    let (a, b) = (
        MeshDistance::new(obj).unwrap(),
        MeshDistance::new(glb).unwrap(),
    );
    for p in points(300, -1.5, 1.5, 9) {
        let (va, vb) = (a.value(&p), b.value(&p));
        assert!((va - vb).abs() < 1e-6, "{p:?}: {va} vs {vb}");
    }
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let path = Path::new("bad.obj");
    for text in [
        "",
        "v 0 0 0\nv 1 0 0\nf 1 2 3\n",
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
        "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        "f 1 2 3\n",
        "v a b c\nf 1 2 3\n",
    ] {
        let r = TriangleMesh::from_obj(text.as_bytes(), path);
        assert!(matches!(r, Err(FitError::Mesh { .. })), "{text:?}: {r:?}");
    }
    for bytes in [
        &b""[..],
        b"glTF\x02\x00\x00\x00",
        b"{\"asset\":{\"version\":\"2.0\"}}",
        b"{not json",
    ] {
        let r = TriangleMesh::from_gltf(bytes, Path::new("bad.glb"));
        assert!(matches!(r, Err(FitError::Mesh { .. })), "{bytes:?}: {r:?}");
    }
    // A GLB cut short.
    let glb = glb_bytes(&icosphere(0), [0.0; 3]);
    for cut in [20, glb.len() / 2, glb.len() - 4] {
        assert!(TriangleMesh::from_gltf(&glb[..cut], Path::new("cut.glb")).is_err());
    }
    // Only degenerate triangles.
    let flat = TriangleMesh {
        positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]],
        triangles: vec![[0, 1, 2]],
    };
    assert!(matches!(
        MeshDistance::new(flat),
        Err(FitError::Mesh {
            source: MeshError::AllDegenerate,
            ..
        })
    ));
    assert!(matches!(
        TriangleMesh::load(Path::new("/nonexistent/x.obj")),
        Err(FitError::Mesh {
            source: MeshError::Io(_),
            ..
        })
    ));
    assert!(matches!(
        TriangleMesh::load(Path::new("x.stl")),
        Err(FitError::Mesh { source: MeshError::UnknownFormat { extension }, .. }) if extension == "stl"
    ));
}

/// Each failure keeps its cause as a typed value: the reader's error (with the place in the
/// file), the limit, the vertex — and the text the CLI prints names the file, then the cause.
#[test]
fn mesh_errors_are_typed_and_keep_their_cause() {
    use ism_export::error::MeshReadError;
    let path = Path::new("m.obj");
    // tobj's own check of face indices: its error is the cause, under the reader's.
    let r = TriangleMesh::from_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", path);
    let Err(err) = r else {
        panic!("index out of range accepted")
    };
    assert!(
        matches!(
            &err,
            FitError::Mesh { path: p, source: MeshError::Read(MeshReadError::Obj(_)) } if p == path
        ),
        "{err:?}"
    );
    assert!(std::error::Error::source(&err).is_some());
    let text = error_text(&err);
    assert!(text.starts_with("mesh m.obj: OBJ: "), "{text}");
    // The limit, with the count and the limit's name.
    let limits = Limits {
        max_simplices: 0,
        ..Limits::default()
    };
    let r =
        TriangleMesh::from_obj_with_limits(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", path, &limits);
    assert!(
        matches!(
            &r,
            Err(FitError::Mesh {
                source: MeshError::Read(MeshReadError::TooLarge {
                    limit: "max_simplices",
                    ..
                }),
                ..
            })
        ),
        "{r:?}"
    );
    let r = TriangleMesh::from_obj(b"v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", path);
    assert!(
        matches!(&r, Err(FitError::Mesh { source: MeshError::NonFinite { vertex: 0, point }, .. }) if point[2].is_nan()),
        "{r:?}"
    );
    let r = TriangleMesh::from_obj(b"v 0 0 0\n", path);
    assert!(
        matches!(
            &r,
            Err(FitError::Mesh {
                source: MeshError::NoTriangles,
                ..
            })
        ),
        "{r:?}"
    );
}

#[test]
fn mutated_files_are_errors_or_meshes_never_panics() {
    // Random byte edits of a valid GLB and OBJ (deterministic LCG). This found gltf-json's
    // unchecked accessor index, now checked before its validation runs.
    let glb = glb_bytes(&icosphere(1), [0.25, -0.5, 1.0]);
    let obj = obj_text(&cube(0.5, [0.0; 3])).into_bytes();
    let mut rng = crate::test_rng::Lcg::new(1);
    let mut next = move || (rng.next_u64() >> 33) as usize;
    for i in 0..4000 {
        let mut b = if i % 2 == 0 { glb.clone() } else { obj.clone() };
        for _ in 0..1 + next() % 4 {
            let k = next() % b.len();
            b[k] = (next() % 256) as u8;
        }
        let r = std::panic::catch_unwind(|| {
            if i % 2 == 0 {
                TriangleMesh::from_gltf(&b, Path::new("f.glb")).map(|m| m.triangles.len())
            } else {
                TriangleMesh::from_obj(&b, Path::new("f.obj")).map(|m| m.triangles.len())
            }
        });
        assert!(r.is_ok(), "panic on {}", String::from_utf8_lossy(&b));
    }
}

/// A closed prism (length 2) whose roof turns by `turn` radians at its ridge (on y = h,
/// along z): triangles oriented outward from the centroid.
fn roof_prism(turn: f64) -> TriangleMesh {
    // Roof faces at ±(90° − turn/2) from the base: apex angle π − turn.
    let h = 1.0 / (0.5 * (std::f64::consts::PI - turn)).tan();
    let mut positions = Vec::new();
    for z in [-1.0, 1.0] {
        positions.extend([[-1.0, 0.0, z], [1.0, 0.0, z], [0.0, h, z]]);
    }
    let quads = [[0, 1, 4, 3], [1, 2, 5, 4], [2, 0, 3, 5]];
    let mut triangles: Vec<[u32; 3]> = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    triangles.extend([[0, 2, 1], [3, 4, 5]]);
    let centre = [0.0, h / 3.0, 0.0];
    for t in &mut triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        if dot(cross(sub(b, a), sub(c, a)), sub(a, centre)) < 0.0 {
            t.swap(1, 2);
        }
    }
    TriangleMesh {
        positions,
        triangles,
    }
}

/// The gradient generators hold the Plantinga–Vegter consequence they are used for: in every
/// box where they agree pairwise, the true gradients (the closest-point directions, sampled)
/// agree pairwise too — on an 82° ridge, a torus (saddles, concave edges) and a bumpy sphere.
/// And they are useful where the box of normals is not: small boxes on the 82° ridge pass.
#[test]
fn gradient_generators_agree_only_where_the_gradients_do() {
    let turn = 82f64.to_radians();
    let mut bumpy = TriangleMesh::icosphere(2, 1.0, [0.0; 3]);
    for (k, p) in bumpy.positions.iter_mut().enumerate() {
        let f = 1.0 + 0.25 * ((k * 7919) % 13) as f64 / 13.0;
        *p = p.map(|x| x * f);
    }
    let h = 1.0 / (0.5 * (std::f64::consts::PI - turn)).tan();
    for (name, mesh) in [
        ("roof", roof_prism(turn)),
        ("torus", torus_mesh(16, 8, 1.0, 0.35)),
        ("bumpy", bumpy),
    ] {
        let d = MeshDistance::new(mesh).unwrap();
        assert!(d.check().is_closed_manifold(), "{name}");
        let mut boxes: Vec<(P3, f64)> = points(300, -1.4, 1.4, 5)
            .into_iter()
            .enumerate()
            .map(|(i, lo)| (lo, [0.02, 0.08, 0.2, 0.5][i % 4]))
            .collect();
        // Boxes centred on the ridge's middle part, from 0.4 down to 0.003 wide.
        let ridge: Vec<(P3, f64)> = (0..40)
            .map(|i| {
                let w = 0.4 * 0.85f64.powi(i);
                let z = -0.5 + (i as f64 * 0.37) % 1.0;
                ([-0.5 * w, h - 0.5 * w, z - 0.5 * w], w)
            })
            .collect();
        if name == "roof" {
            boxes.extend(&ridge);
        }
        let (mut agreed, mut ridge_passed) = (0, 0);
        for (i, (lo, w)) in boxes.iter().enumerate() {
            let hi = lo.map(|x| x + w);
            let mut gens = Vec::new();
            assert!(d.gradient_generators(lo, &hi, &mut gens), "{name}");
            if !crate::fit::topology::unit_vectors_agree(3, &gens) {
                continue;
            }
            agreed += 1;
            ridge_passed += usize::from(i >= 300);
            let grads: Vec<P3> = points(60, 0.0, 1.0, i as u64 + 1)
                .into_iter()
                .map(|s| {
                    let p = [0, 1, 2].map(|k| lo[k] + w * s[k]);
                    let mut g = [0.0; 3];
                    d.gradient(&p, &mut g);
                    g
                })
                .collect();
            for a in &grads {
                for b in &grads {
                    assert!(dot(*a, *b) > 0.0, "{name} box {lo:?} +{w}: {a:?} {b:?}");
                }
            }
        }
        assert!(agreed > 10, "{name}: {agreed} boxes agreed");
        if name == "roof" {
            assert!(ridge_passed > 10, "{ridge_passed} ridge boxes passed");
            // The component-wise box of the two roof normals cannot pass there.
            let (lo, w) = ridge[ridge.len() - 1];
            let hi = lo.map(|x| x + w);
            let enc = d.enclose(&lo, &hi).unwrap();
            let mut dotb = Interval::point(0.0);
            for gk in &enc.gradient {
                dotb = dotb + *gk * *gk;
            }
            assert!(enc.value.contains(0.0) && dotb.lo <= 0.0, "{enc:?}");
        }
    }
}

#[test]
fn enclosures_contain_point_values_and_gradients() {
    let d = MeshDistance::new(icosphere(2)).unwrap();
    let corners = points(60, -1.3, 1.1, 13);
    let mut passed_near_surface = 0;
    for (i, lo) in corners.iter().enumerate() {
        let w = [0.02, 0.08, 0.2][i % 3];
        let hi = lo.map(|x| x + w);
        let enc = d.enclose(lo, &hi).unwrap();
        for s in points(40, 0.0, 1.0, i as u64) {
            let p = [0, 1, 2].map(|k| lo[k] + w * s[k]);
            let mut g = [0.0; 3];
            let v = d.gradient(&p, &mut g);
            assert!(enc.value.contains(v), "{p:?}");
            if enc.value.contains(0.0) {
                for (bound, gk) in enc.gradient.iter().zip(g) {
                    assert!(bound.contains(gk), "{p:?} {gk}: {enc:?}");
                }
            }
        }
        if enc.value.contains(0.0) {
            let mut dot = Interval::point(0.0);
            for gk in &enc.gradient {
                dot = dot + *gk * *gk;
            }
            passed_near_surface += usize::from(dot.lo > 0.0);
        }
    }
    // Small boxes on a smooth mesh pass the test (the enclosure is useful, not just safe).
    assert!(passed_near_surface > 0);
}

/// The brute-force candidate set of the box `[lo, hi]` (see `candidates_are_the_brute_force_set`):
/// per sub-box of the 4³ split, every triangle within (distance from the centre to its closest
/// triangle, over all triangles) + 2 × half-diagonal + margin of the centre.
fn brute_candidates(d: &MeshDistance, tris: &[[P3; 3]], lo: &P3, hi: &P3) -> Vec<u32> {
    let dist2 = |p: P3, v: [P3; 3]| {
        let e = sub(p, closest_point_on_triangle(p, v));
        dot(e, e)
    };
    let parts = 1usize << GRADIENT_SPLIT_LEVELS;
    let mut ids = Vec::new();
    for i in 0..parts * parts * parts {
        let j = [i % parts, (i / parts) % parts, i / (parts * parts)];
        let at = |k: usize, j: usize| {
            if j == parts {
                hi[k]
            } else {
                lo[k] + (hi[k] - lo[k]) * (j as f64 / parts as f64)
            }
        };
        let sub_lo = [0, 1, 2].map(|k| at(k, j[k]));
        let sub_hi = [0, 1, 2].map(|k| at(k, j[k] + 1));
        let (c, half) = centre_and_half_diagonal(&sub_lo, &sub_hi);
        let nearest = tris
            .iter()
            .map(|&v| dist2(c, v))
            .fold(f64::INFINITY, f64::min)
            .sqrt();
        let r = nearest + 2.0 * half + 2.0 * VALUE_MARGIN_REL * d.scale;
        ids.extend((0..tris.len() as u32).filter(|&t| dist2(c, tris[t as usize]) <= r * r));
    }
    ids.sort_unstable();
    ids.dedup();
    ids
}

/// A box's [`PvWitness`] against brute force over all triangles: its normal is that of a
/// triangle nearest to the box's centre (linear scan), which is in the brute-force candidate set
/// of every larger box holding the box (and so its normal among those boxes' generators, bit for
/// bit) and inside their gradient enclosures; its value is `value_bounds`', bit for bit, and
/// holds the signed distance at the centre (side by the brute-force winding number); the unit
/// gradient flag is `enclose`'s. On a torus mesh and the 82° roof prism, boxes on and off the
/// surface from 0.005 to 0.4 wide, each inside 3 larger boxes it lies anywhere in.
#[test]
fn pv_witnesses_are_nearest_triangles_and_generators_of_every_box_around_them() {
    for mesh in [
        torus_mesh(24, 12, 1.0, 0.35),
        roof_prism(82f64.to_radians()),
    ] {
        let d = MeshDistance::new(mesh).unwrap();
        let tris: Vec<[P3; 3]> = d.surface_triangles().unwrap();
        let dist2 = |p: P3, v: [P3; 3]| {
            let e = sub(p, closest_point_on_triangle(p, v));
            dot(e, e)
        };
        let (mut checked, mut near_surface) = (0, 0);
        let corners = points(120, -1.5, 1.3, 47);
        let offsets = points(360, 0.0, 1.0, 53);
        for (i, lo) in corners.iter().enumerate() {
            let w = [0.005, 0.03, 0.1, 0.4][i % 4];
            let hi = lo.map(|x| x + w);
            let wit = d.pv_witness(lo, &hi).unwrap();
            let (c, _) = centre_and_half_diagonal(lo, &hi);
            let best = tris
                .iter()
                .map(|&v| dist2(c, v))
                .fold(f64::INFINITY, f64::min);
            let nearest: Vec<u32> = (0..tris.len() as u32)
                .filter(|&t| dist2(c, tris[t as usize]) == best)
                .collect();
            let t = *nearest
                .iter()
                .find(|&&t| d.normals[t as usize] == wit.normal)
                .unwrap_or_else(|| panic!("box {i}: {:?} is no nearest triangle's", wit.normal));
            assert_eq!(wit.value, d.value_bounds(lo, &hi), "box {i}");
            let inside = d.winding_number_brute_force(c) > 0.5;
            let signed = if inside { -best.sqrt() } else { best.sqrt() };
            assert!(
                wit.value.contains(signed),
                "box {i}: {signed} {:?}",
                wit.value
            );
            let enc = d.enclose(lo, &hi).unwrap();
            let unit = enc.gradient.iter().all(|g| g.lo == -1.0 && g.hi == 1.0);
            assert_eq!(wit.unit_gradient, !wit.value.contains(0.0), "box {i}");
            assert!(!wit.unit_gradient || unit, "box {i}");
            near_surface += usize::from(!wit.unit_gradient);
            for o in &offsets[3 * i..3 * i + 3] {
                // A box 1.5–4× as wide holding [lo, hi] at offset `o` of its slack.
                let s = w * (1.5 + 2.5 * o[0]);
                let big_lo = [0, 1, 2].map(|k| lo[k] - (s - w) * o[k]);
                let big_hi = big_lo.map(|x| x + s);
                assert!(brute_candidates(&d, &tris, &big_lo, &big_hi).contains(&t));
                let mut gens = Vec::new();
                assert!(d.gradient_generators(&big_lo, &big_hi, &mut gens));
                assert!(gens.chunks_exact(3).any(|g| g == wit.normal), "box {i}");
                let enc = d.enclose(&big_lo, &big_hi).unwrap();
                for (g, x) in enc.gradient.iter().zip(wit.normal) {
                    let tol = crate::expr::GENERATOR_ERROR;
                    assert!(g.lo - tol <= x && x <= g.hi + tol, "box {i}: {x} {g:?}");
                }
                checked += 1;
            }
        }
        assert!(
            checked == 360 && near_surface > 10,
            "{near_surface} near the surface"
        );
    }
}

/// [`MeshDistance::candidates_superset`] of some of a box's 4³ parts is the brute-force set of
/// its definition — the triangles within |g(C)| + 2H + 4 margins of each part's centre `C` —
/// and holds every part's brute-force candidate set; it is not the whole mesh. On a torus mesh,
/// cells from 0.02 to 0.5 wide, on and off the surface, with every part or every third.
#[test]
fn the_candidate_superset_holds_every_parts_brute_force_candidates() {
    let d = MeshDistance::new(torus_mesh(24, 12, 1.0, 0.35)).unwrap();
    let tris: Vec<[P3; 3]> = d.surface_triangles().unwrap();
    let dist2 = |p: P3, v: [P3; 3]| {
        let e = sub(p, closest_point_on_triangle(p, v));
        dot(e, e)
    };
    let mut small = 0;
    for (i, lo) in points(60, -1.5, 1.2, 59).iter().enumerate() {
        let w = [0.02, 0.08, 0.2, 0.5][i % 4];
        let parts: Vec<(P3, P3)> = (0..64)
            .filter(|j| i % 2 == 0 || j % 3 == 0)
            .map(|j| {
                let at = [j % 4, (j / 4) % 4, j / 16];
                let l = [0, 1, 2].map(|k| lo[k] + w * at[k] as f64 / 4.0);
                (l, l.map(|x| x + w / 4.0))
            })
            .collect();
        let boxes: Vec<(&[f64], &[f64])> = parts.iter().map(|(l, h)| (&l[..], &h[..])).collect();
        let got = d.candidates_superset(&boxes);
        let mut expected: Vec<u32> = Vec::new();
        for (l, h) in &parts {
            let (c, half) = centre_and_half_diagonal(l, h);
            let g = tris
                .iter()
                .map(|&v| dist2(c, v))
                .fold(f64::INFINITY, f64::min)
                .sqrt();
            let r = g + 2.0 * half + 4.0 * VALUE_MARGIN_REL * d.scale;
            expected
                .extend((0..tris.len() as u32).filter(|&t| dist2(c, tris[t as usize]) <= r * r));
            for t in brute_candidates(&d, &tris, l, h) {
                assert!(got.binary_search(&t).is_ok(), "cell {i}: {t} missing");
            }
        }
        expected.sort_unstable();
        expected.dedup();
        assert_eq!(got, expected, "cell {i}");
        small += usize::from(got.len() * 4 < tris.len());
    }
    assert!(
        small > 20,
        "{small} of 60 supersets under a quarter of the mesh"
    );
}

/// `distance_bound` (branch and bound from the thread's previous triangle) is the linear scan's
/// least distance, bit for bit, along a walk of nearby points (the measure's pattern) and at
/// scattered ones, on a torus mesh and a cube (ties on shared edges and corners).
#[test]
fn the_distance_bound_is_the_linear_scans_least_distance() {
    for mesh in [torus_mesh(24, 12, 1.0, 0.35), cube(0.5, [0.1, -0.2, 0.05])] {
        let d = MeshDistance::new(mesh).unwrap();
        let tris: Vec<[P3; 3]> = d.surface_triangles().unwrap();
        let mut queries = points(300, -1.6, 1.6, 61);
        let walk: Vec<P3> = (0..300)
            .map(|i| {
                let a = i as f64 * 0.02;
                [1.2 * a.cos(), 1.2 * a.sin(), 0.3 * (3.0 * a).sin()]
            })
            .collect();
        queries.extend(walk);
        queries.extend(d.mesh.positions.iter().copied());
        for (i, p) in queries.iter().enumerate() {
            let expected = tris
                .iter()
                .map(|&v| norm(sub(*p, closest_point_on_triangle(*p, v))))
                .fold(f64::INFINITY, f64::min);
            let got = d.distance_bound(p, f64::INFINITY);
            assert_eq!(got.to_bits(), expected.to_bits(), "query {i} {p:?}");
        }
    }
}

/// The candidate triangles of a box (the R-tree's nearest-point queries bounded by the previous
/// sub-box's triangle, range queries, the per-thread memo) are exactly the brute-force set: per
/// sub-box of the 4³ split, every triangle within (distance from the centre to its closest
/// triangle, over all triangles) + 2 × half-diagonal + margin of the centre — on a torus mesh
/// (saddles, concave edges), boxes on and off the surface, each asked twice with more than the
/// memo's capacity of other boxes between (so both a memo hit and a recomputation are compared).
#[test]
fn candidates_are_the_brute_force_set() {
    let d = MeshDistance::new(torus_mesh(24, 12, 1.0, 0.35)).unwrap();
    let tris: Vec<[P3; 3]> = d.surface_triangles().unwrap();
    let brute = |lo: &P3, hi: &P3| brute_candidates(&d, &tris, lo, hi);
    let boxes: Vec<(P3, P3)> = points(200, -1.5, 1.2, 17)
        .into_iter()
        .enumerate()
        .map(|(i, lo)| {
            let w = [0.01, 0.05, 0.15, 0.4][i % 4];
            (lo, lo.map(|x| x + w))
        })
        .collect();
    let expected: Vec<Vec<u32>> = boxes.iter().map(|(lo, hi)| brute(lo, hi)).collect();
    for pass in 0..2 {
        for (i, (lo, hi)) in boxes.iter().enumerate() {
            let got = d.candidates(lo, hi);
            assert_eq!(
                &got[..],
                &expected[i][..],
                "pass {pass}, box {i}: {lo:?} {hi:?}"
            );
            // Asked again at once: the memo's answer.
            assert_eq!(&d.candidates(lo, hi)[..], &expected[i][..], "memo, box {i}");
        }
    }
    // Not every triangle everywhere: the small boxes' sets are a small part of the mesh.
    let small = (0..boxes.len())
        .step_by(4)
        .filter(|&i| expected[i].len() * 10 < tris.len())
        .count();
    assert!(
        small > 40,
        "{small} of 50 small boxes with < 10 % of the triangles"
    );
}

/// The nearest-triangle search is a linear scan's answer — the smallest `(distance², id)` over
/// every triangle — whatever the hint: far hints, the nearest triangle itself, points on the
/// surface (mesh vertices and edge midpoints, where several triangles tie at distance 0), off it,
/// and far away; on a torus and on an axis-aligned cube (boxes and triangles share faces there).
#[test]
fn the_nearest_triangle_is_the_linear_scans_whatever_the_hint() {
    for mesh in [torus_mesh(24, 12, 1.0, 0.35), cube(0.5, [0.1, -0.2, 0.05])] {
        let d = MeshDistance::new(mesh).unwrap();
        let tris: Vec<[P3; 3]> = d.surface_triangles().unwrap();
        let in_tree: Vec<u32> = d.tree.iter().map(|t| t.id).collect();
        let scan = |p: P3| -> (f64, u32) {
            let mut best = (f64::INFINITY, u32::MAX);
            for &t in &in_tree {
                let e = sub(p, closest_point_on_triangle(p, tris[t as usize]));
                let d2 = dot(e, e);
                if d2 < best.0 || (d2 == best.0 && t < best.1) {
                    best = (d2, t);
                }
            }
            best
        };
        let mut queries = points(300, -1.6, 1.6, 29);
        queries.extend(points(20, -9.0, 9.0, 31));
        queries.extend(d.mesh.positions.iter().copied());
        for t in &tris {
            queries.push([0, 1, 2].map(|k| 0.5 * (t[0][k] + t[1][k])));
        }
        let mut ties = 0;
        for (i, &p) in queries.iter().enumerate() {
            let expected = scan(p);
            if expected.0 == 0.0 {
                ties += 1;
            }
            for hint in [
                in_tree[i % in_tree.len()],
                in_tree[(7 * i + 3) % in_tree.len()],
                expected.1,
            ] {
                let got = d.nearest_triangle(p, hint);
                assert_eq!(got.1, expected.1, "query {i} {p:?}, hint {hint}");
                assert_eq!(got.0.to_bits(), expected.0.to_bits(), "query {i}");
                let (q, t) = d.closest_point_near(p, hint);
                assert_eq!(t, expected.1);
                assert_eq!(q, closest_point_on_triangle(p, tris[t as usize]));
            }
        }
        // The on-surface queries (vertices, edge midpoints) are there and tie at distance 0.
        assert!(
            ties >= d.mesh.positions.len(),
            "{ties} queries on the surface"
        );
    }
}

/// The inlined box distance is rstar's `AABB::distance_2`, bit for bit: points inside, on a face,
/// beyond a face, an edge and a corner of random boxes.
#[test]
fn the_box_distance_is_rstars() {
    let corners = points(400, -2.0, 2.0, 41);
    let queries = points(400, -3.0, 3.0, 43);
    for (i, pair) in corners.chunks_exact(2).enumerate() {
        let env = AABB::from_corners(pair[0], pair[1]);
        let (lo, hi) = (env.lower(), env.upper());
        let mut probes: Vec<P3> = queries[i..i + 8].to_vec();
        probes.push(lo);
        probes.push(hi);
        probes.push([lo[0], 0.5 * (lo[1] + hi[1]), hi[2] + 0.3]);
        probes.push([0.5 * (lo[0] + hi[0]); 3]);
        for p in probes {
            assert_eq!(
                box_distance_2(&env, &p).to_bits(),
                env.distance_2(&p).to_bits(),
                "box {i}, point {p:?}"
            );
        }
    }
}
