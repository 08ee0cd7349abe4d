//! Position maps of known meshes, posed maps, head maps.

use f3g_rig::{Mesh, ModelSpec, SkinWeights};
use f3g_template::canonical::CanonicalPose;
use f3g_template::head::DENSIFY;
use f3g_template::mesh::SurfaceQuery;
use f3g_template::template::{LABEL_BODY, Template};
use f3g_template::{HeadMaps, Poser, PositionMaps, TransferOptions, posed_positions};
use glam::Vec3;

/// An axis-aligned box with outward-facing triangles.
fn cube(half: f32) -> Mesh {
    let v: Vec<Vec3> = (0..8)
        .map(|i| {
            Vec3::new(
                if i & 1 == 0 { -half } else { half },
                if i & 2 == 0 { -half } else { half },
                if i & 4 == 0 { -half } else { half },
            )
        })
        .collect();
    let quads = [
        [0, 2, 3, 1],
        [4, 5, 7, 6],
        [0, 1, 5, 4],
        [2, 6, 7, 3],
        [0, 4, 6, 2],
        [1, 3, 7, 5],
    ];
    let triangles = quads
        .iter()
        .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
        .collect();
    Mesh {
        vertices: v,
        triangles,
    }
}

/// A UV sphere with outward-facing triangles.
fn sphere(radius: f32, rings: u32, segments: u32) -> Mesh {
    let mut vertices = vec![Vec3::new(0.0, radius, 0.0)];
    for r in 1..rings {
        let theta = std::f32::consts::PI * r as f32 / rings as f32;
        for s in 0..segments {
            let phi = std::f32::consts::TAU * s as f32 / segments as f32;
            vertices.push(
                radius
                    * Vec3::new(
                        theta.sin() * phi.cos(),
                        theta.cos(),
                        theta.sin() * phi.sin(),
                    ),
            );
        }
    }
    vertices.push(Vec3::new(0.0, -radius, 0.0));
    let last = vertices.len() as u32 - 1;
    let ring = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
    let mut triangles = Vec::new();
    for s in 0..segments {
        triangles.push([0, ring(1, s + 1), ring(1, s)]);
        triangles.push([last, ring(rings - 1, s), ring(rings - 1, s + 1)]);
        for r in 1..rings - 1 {
            triangles.push([ring(r, s), ring(r, s + 1), ring(r + 1, s + 1)]);
            triangles.push([ring(r, s), ring(r + 1, s + 1), ring(r + 1, s)]);
        }
    }
    Mesh {
        vertices,
        triangles,
    }
}

fn rigid_template(mesh: Mesh) -> Template {
    let n = mesh.vertices.len();
    Template {
        model: "builtin".into(),
        canonical: f3g_rig::RigParams {
            pose: vec![],
            identity: vec![],
            expression: vec![],
        },
        skin: SkinWeights::from_lists(&vec![vec![(0, 1.0)]; n], 1).unwrap(),
        vertex_label: vec![LABEL_BODY; n],
        body_vertex: vec![None; n],
        mesh,
    }
}

#[test]
fn a_box_gives_the_analytic_maps() {
    let t = rigid_template(cube(0.5));
    let maps = PositionMaps::build(&t, 20, Some(2.0)).unwrap();
    let r = 20;
    // Pixel size 0.1 m; centres at -0.95, ..., 0.95: the box covers columns/rows 5..15 on each side.
    assert_eq!(maps.len(), 2 * 10 * 10);
    for (g, &p) in maps.pixels.iter().enumerate() {
        let (row, col) = (p / (2 * r), p % (2 * r));
        let (side, c) = (col / r, col % r);
        assert!((5..15).contains(&row) && (5..15).contains(&c));
        let expected = Vec3::new(
            -0.95 + 0.1 * c as f32,
            0.95 - 0.1 * row as f32,
            if side == 0 { 0.5 } else { -0.5 },
        );
        assert!(
            (maps.positions[g] - expected).length() < 1e-5,
            "{:?} vs {expected:?}",
            maps.positions[g]
        );
        // Vertex normals of a box point along the corner diagonals; interpolated, they still
        // face the viewer of their side.
        let facing = if side == 0 {
            maps.normals[g].z
        } else {
            -maps.normals[g].z
        };
        assert!(facing > 0.0, "normal {:?}", maps.normals[g]);
    }
}

#[test]
fn a_sphere_maps_to_its_surface_and_front_and_back_align() {
    let mesh = sphere(0.8, 48, 96);
    let t = rigid_template(mesh.clone());
    let r = 64;
    let maps = PositionMaps::build(&t, r, Some(2.0)).unwrap();
    let query = SurfaceQuery::new(&mesh).unwrap();
    let mask = maps.mask();
    for (g, &p) in maps.pixels.iter().enumerate() {
        let (row, col) = (p / (2 * r), p % (2 * r));
        let centre = glam::Vec2::new(
            maps.origin.x + (col % r) as f32 * maps.pixel_size + 0.5 * maps.pixel_size,
            maps.origin.y - (row as f32 + 0.5) * maps.pixel_size,
        );
        let x = maps.positions[g];
        // The Gaussian sits at the pixel centre in x/y, on the mesh, well within half a texel.
        assert!((x.truncate() - centre).length() < 1e-4);
        assert!(query.closest(x).distance < 1e-4);
        // Front points look forward, back points backward, and both are near the analytic sphere.
        let front = col < r;
        assert_eq!(x.z > 0.0, front);
        let analytic = (0.64 - centre.length_squared()).max(0.0).sqrt();
        assert!(
            (x.z.abs() - analytic).abs() < 0.02,
            "z {} vs {analytic}",
            x.z
        );
        // The other side of a convex body is covered at the same (x, y).
        let other = row * 2 * r + if front { col + r } else { col - r };
        assert!(mask[other], "pixel {p} has no partner");
    }
}

#[test]
fn a_fully_covered_head_crop_densifies_to_four_times_the_texels() {
    let t = rigid_template(cube(0.5));
    let maps = PositionMaps::build(&t, 20, Some(2.0)).unwrap();
    // The one joint of the rigid template is the head: everything is head.
    let head = HeadMaps::build(&maps, &[0], DENSIFY).unwrap();
    let [_, _, side] = head.crop;
    assert_eq!(side, 11);
    assert_eq!(head.size, 22);
    // Inside the 10×10 covered block all texels are valid; at its border the validity rule
    // (≥ 0.5) keeps exactly the texels whose sample point lies inside the block: 20×20 per side.
    assert_eq!(head.len(), 2 * 20 * 20);
    for (sources, x) in head.sources.iter().zip(&head.positions) {
        assert!((sources.iter().map(|s| s.1).sum::<f32>() - 1.0).abs() < 1e-5);
        assert!(
            x.z.abs() > 0.49,
            "densified points stay on the faces of the box"
        );
    }
    // Density 4: 4 × 4 texels per source texel inside the block (40×40 per side); at its
    // corners the validity rule drops a texel whose sample point lies outside the block along
    // both axes (coverage 0.625² < 0.5), where the crop's border clamp does not cover it.
    let dense = HeadMaps::build(&maps, &[0], 4).unwrap();
    assert_eq!(dense.size, 44);
    assert!(
        (2 * 40 * 40 - 8..=2 * 40 * 40).contains(&dense.len()),
        "{}",
        dense.len()
    );
    assert!(HeadMaps::build(&maps, &[0], 0).is_err());
}

#[test]
fn builtin_maps_posed_at_the_canonical_pose_equal_the_canonical_maps() {
    let model = ModelSpec::Builtin;
    let (t, _) = Template::build(
        &model.load().unwrap(),
        &CanonicalPose::default(),
        None,
        None,
        &TransferOptions::default(),
    )
    .unwrap();
    let rig = model.load().unwrap();
    // The legs are spread: each hip turned 25° about its forward axis.
    let names = rig.pose_param_names();
    let hip = |n: &str| t.canonical.pose[names.iter().position(|p| p == n).unwrap()];
    assert_eq!(
        (hip("upperleg01.L_rz"), hip("upperleg01.R_rz")),
        (25f32.to_radians(), -25f32.to_radians())
    );
    let maps = PositionMaps::build(&t, 96, None).unwrap();
    let poser = Poser::new(&rig, &t).unwrap();
    let posed = posed_positions(&poser, &maps, &t.canonical).unwrap();
    let worst = posed
        .iter()
        .zip(&maps.positions)
        .map(|(a, b)| (*a - *b).length())
        .fold(0.0, f32::max);
    assert!(worst < 1e-5, "worst {worst}");
    // Moving the root does not move root-relative posed maps.
    let mut moved = t.canonical.clone();
    moved.pose[0] = 1.0;
    moved.pose[names.iter().position(|n| n == "root_ry").unwrap()] = 0.7;
    let again = posed_positions(&poser, &maps, &moved).unwrap();
    assert!(
        again
            .iter()
            .zip(&posed)
            .all(|(a, b)| (*a - *b).length() < 1e-5)
    );

    let head_joints = rig.head_joints().unwrap();
    let head = HeadMaps::build(&maps, &head_joints, DENSIFY).unwrap();
    assert!(!head.is_empty());
    let head_weight = |g: usize| {
        head.skin
            .influences(g)
            .filter(|(j, _)| head_joints.contains(j))
            .map(|(_, w)| w)
            .sum::<f32>()
    };
    let on_head = (0..head.len()).filter(|&g| head_weight(g) > 0.5).count();
    assert!(
        on_head * 2 > head.len(),
        "most face Gaussians are on the head ({on_head} of {})",
        head.len()
    );
    assert!(head.sources.iter().all(|s| !s.is_empty() && s.len() <= 4));
}

#[test]
fn expressions_and_shape_move_the_template_with_the_posed_body_model() {
    let model = ModelSpec::Builtin;
    let rig = model.load().unwrap();
    let mut identity = vec![0.0; rig.identity.len()];
    identity[0] = 0.4; // a little more masculine than the average
    let (t, _) = Template::build(
        &model.load().unwrap(),
        &CanonicalPose::default(),
        Some(&identity),
        None,
        &TransferOptions::default(),
    )
    .unwrap();
    assert!(t.body_vertex.iter().all(Option::is_some));
    let maps = PositionMaps::build(&t, 128, None).unwrap();
    let poser = Poser::new(&rig, &t).unwrap();
    // A frame with a smile, a blink, a brow raise and an open jaw, turned a little.
    let mut frame = t.canonical.clone();
    for (name, v) in [
        ("mouth-corner-puller", 1.0),
        ("eye-left-closure", 1.0),
        ("eyebrows-left-up", 1.0),
    ] {
        frame.expression[rig.expression.names.iter().position(|n| n == name).unwrap()] = v;
    }
    let names = rig.pose_param_names();
    frame.pose[names.iter().position(|n| n == "jaw_rx").unwrap()] = 0.2;
    frame.pose[names.iter().position(|n| n == "head_ry").unwrap()] = 0.3;
    let (transforms, posed) = poser.frame(&frame, false).unwrap();
    let moved = maps.interpolate(&poser.displacements(&t, &posed));
    let canonical: Vec<Vec3> = maps
        .positions
        .iter()
        .zip(&moved)
        .map(|(p, d)| *p + *d)
        .collect();
    let gaussians = f3g_rig::skin_points(&transforms, &maps.skin, &canonical);
    // The same surface points of the posed body model (barycentric on its vertices).
    let mut worst = 0.0f32;
    let mut expressive = 0;
    for (g, (tri, b)) in maps.corners.iter().zip(&maps.bary).enumerate() {
        let surface: Vec3 = (0..3)
            .map(|k| posed.vertices[t.body_vertex[tri[k] as usize].unwrap() as usize] * b[k])
            .sum();
        worst = worst.max((surface - gaussians[g]).length());
        expressive += (moved[g].length() > 1e-3) as usize;
    }
    // LBS of interpolated points with interpolated weights differs from interpolating skinned
    // vertices only to second order: well under a millimetre on this mesh.
    assert!(worst < 1e-3, "worst {worst}");
    // The face covers ~15 × 15 texels per side at R = 128; the expression moves part of it.
    let largest = moved.iter().map(|d| d.length()).fold(0.0, f32::max);
    assert!(
        expressive >= 10 && largest > 3e-3,
        "{expressive} Gaussians moved by the expression, at most {largest} m"
    );
    // Without expression nor correctives, nothing moves.
    let (_, still) = poser.frame(&t.canonical, false).unwrap();
    assert!(
        poser
            .displacements(&t, &still)
            .iter()
            .all(|d| d.length() < 1e-6)
    );
    let bad = Template::build(
        &model.load().unwrap(),
        &CanonicalPose::default(),
        Some(&[1.0]),
        None,
        &TransferOptions::default(),
    );
    assert!(bad.err().unwrap().to_string().contains("identity"));
}
