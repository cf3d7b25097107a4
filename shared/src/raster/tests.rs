//! Rasterizer tests.
#![allow(clippy::unwrap_used)]

use glam::{Mat4, Vec3};

use super::*;

const W: u32 = 16;
const H: u32 = 16;

/// Orthographic camera where world (x, y) maps to pixel (x + w/2, h/2 − y); nearer = larger z.
fn pixel_camera(_w: u32, h: u32) -> Camera {
    Camera::look_at(
        Vec3::new(0.0, 0.0, 10.0),
        Vec3::ZERO,
        Vec3::Y,
        Projection::Orthographic {
            half_height: h as f32 / 2.0,
            near: 1.0,
            far: 20.0,
        },
    )
}

/// World point of pixel-space point (px, py) at height z, for [`pixel_camera`].
fn pix(px: f32, py: f32, z: f32, w: u32, h: u32) -> Vec3 {
    Vec3::new(px - w as f32 / 2.0, h as f32 / 2.0 - py, z)
}

/// A mesh of triangles given in pixel space, one item per triangle unless `items` says.
fn mesh_of(tris: &[[Vec3; 3]], items: &[u32]) -> RasterMesh {
    let mut m = RasterMesh::default();
    for (k, t) in tris.iter().enumerate() {
        let b = m.positions.len() as u32;
        m.positions.extend_from_slice(t);
        m.uvs.extend_from_slice(&[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        m.indices.extend_from_slice(&[b, b + 1, b + 2]);
        m.item_of_triangle.push(items.get(k).copied().unwrap_or(k as u32));
    }
    m
}

fn opaque() -> Vec<RasterMaterial> {
    vec![RasterMaterial::default()]
}

fn covered_set(frame: &Frame, item: u32) -> Vec<(u32, u32)> {
    (0..frame.pixel_count())
        .filter(|&k| frame.item[k] == item)
        .map(|k| ((k as u32) % frame.width, (k as u32) / frame.width))
        .collect()
}

#[test]
fn known_triangle_and_quad_cover_exact_pixels_once() {
    let p = |x: f32, y: f32| pix(x, y, 0.0, W, H);
    // Vertices on pixel centres: the top and left edges include centres on them, the
    // hypotenuse (a right edge) does not.
    let upper = [p(2.5, 2.5), p(10.5, 2.5), p(2.5, 10.5)];
    let lower = [p(10.5, 2.5), p(10.5, 10.5), p(2.5, 10.5)];
    let mats = opaque();
    for winding in [false, true] {
        let (u, l) = if winding {
            ([upper[0], upper[2], upper[1]], [lower[0], lower[2], lower[1]])
        } else {
            (upper, lower)
        };
        let mesh = mesh_of(&[u, l], &[]);
        let scene = Scene::single(&mesh, &mats, &[]);
        let frame = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
        let a = covered_set(&frame, 0);
        let want_a: Vec<(u32, u32)> = (0..H)
            .flat_map(|y| (0..W).map(move |x| (x, y)))
            .filter(|&(x, y)| x >= 2 && y >= 2 && x + y <= 11)
            .collect();
        assert_eq!(a, want_a);
        assert_eq!(covered_set(&frame, 1).len(), 28);
        // The quad covers exactly the 8×8 square, and the A-buffer shows no pixel twice.
        let ab = ABuffer::render(&scene, &pixel_camera(W, H), W, H).unwrap();
        for y in 0..H {
            for x in 0..W {
                let inside = (2..=9).contains(&x) && (2..=9).contains(&y);
                let k = (y * W + x) as usize;
                assert_eq!(ab.fragments(k).len(), usize::from(inside), "pixel {x},{y}");
                assert_eq!(frame.item[k] != EMPTY_ITEM, inside);
            }
        }
    }
}

#[test]
fn shared_edges_never_double_cover() {
    // Random fans around random centres, perspective camera: every pixel at most once, and
    // the fan's interior has no holes (the A-buffer count equals the item buffer coverage).
    let mut seed = 12345u64;
    let mut rnd = move || {
        seed = seed
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((seed >> 33) as f32) / (1u64 << 31) as f32
    };
    let cam = Camera::look_at(
        Vec3::new(0.3, 0.2, 5.0),
        Vec3::ZERO,
        Vec3::Y,
        Projection::Perspective {
            fov_y: 1.0,
            near: 0.5,
            far: 20.0,
        },
    );
    let mats = opaque();
    for _ in 0..20 {
        let c = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
        let n = 3 + (rnd() * 10.0) as usize;
        let ring: Vec<Vec3> = (0..n)
            .map(|i| {
                let a = i as f32 / n as f32 * std::f32::consts::TAU;
                c + Vec3::new(a.cos(), a.sin(), 0.3 * (rnd() - 0.5)) * (0.3 + rnd())
            })
            .collect();
        let tris: Vec<[Vec3; 3]> = (0..n).map(|i| [c, ring[i], ring[(i + 1) % n]]).collect();
        let mesh = mesh_of(&tris, &[]);
        let scene = Scene::single(&mesh, &mats, &[]);
        let ab = ABuffer::render(&scene, &cam, 37, 29).unwrap();
        for k in 0..(37 * 29) {
            assert!(ab.fragments(k).len() <= 1, "pixel {k} covered twice");
        }
    }
}

/// Two triangles covering pixels 1..15 × 1..15 (14 × 14 pixel centres) at depth `z`.
fn square_at(z: f32) -> [[Vec3; 3]; 2] {
    let p = |x: f32, y: f32| pix(x, y, z, W, H);
    [
        [p(1.0, 1.0), p(15.0, 1.0), p(15.0, 15.0)],
        [p(1.0, 1.0), p(15.0, 15.0), p(1.0, 15.0)],
    ]
}

#[test]
fn nearer_wins_and_ties_break_by_item() {
    let mats = opaque();
    for order in [false, true] {
        let (far, near) = (square_at(-1.0), square_at(2.0));
        let (tris, items) = if order {
            (vec![far[0], far[1], near[0], near[1]], [7, 7, 3, 3])
        } else {
            (vec![near[0], near[1], far[0], far[1]], [3, 3, 7, 7])
        };
        let mesh = mesh_of(&tris, &items);
        let scene = Scene::single(&mesh, &mats, &[]);
        let f = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
        let k = (8 * W + 8) as usize;
        assert_eq!(f.item[k], 3);
        // Nearer is smaller depth: z = 2 at view distance 8 of near 1 far 20 → 7/19.
        assert!((f.depth[k] - 7.0 / 19.0).abs() < 1e-5);
        assert_eq!(f.item[0], EMPTY_ITEM);
        assert_eq!(f.depth[0], f32::INFINITY);
        // Same depth: the smaller item wins whatever the order.
        let q = square_at(0.0);
        let items2 = if order { [9, 9, 4, 4] } else { [4, 4, 9, 9] };
        let mesh = mesh_of(&[q[0], q[1], q[0], q[1]], &items2);
        let scene = Scene::single(&mesh, &mats, &[]);
        let f = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
        assert_eq!(f.item[k], 4);
    }
}

#[test]
fn retain_cuts_lists_and_rebuilds_the_item_index() {
    // Two stacked quads (items 3 near, 7 far) over 14 × 14 pixels; cut the far one on the
    // left half: its pixels there are gone from the lists and from `pixels_of`, a tracker
    // built on the copy sees the left half empty once 3 is removed.
    let mats = opaque();
    let (near, far) = (square_at(2.0), square_at(-1.0));
    let mesh = mesh_of(&[near[0], near[1], far[0], far[1]], &[3, 3, 7, 7]);
    let scene = Scene::single(&mesh, &mats, &[]);
    let ab = ABuffer::render(&scene, &pixel_camera(W, H), W, H).unwrap();
    let left = |p: u32| p % W < 8;
    let cut = ab.retain(|p, f| !(f.item == 7 && left(p)));
    assert_eq!(cut.fragment_count(), ab.fragment_count() - 7 * 14);
    assert_eq!(cut.pixels_of(3), ab.pixels_of(3));
    assert!(cut.pixels_of(7).iter().all(|&p| !left(p)));
    assert_eq!(cut.pixels_of(7).len(), 7 * 14);
    for p in 0..(W * H) as usize {
        let want: Vec<Fragment> = ab
            .fragments(p)
            .iter()
            .copied()
            .filter(|f| !(f.item == 7 && left(p as u32)))
            .collect();
        assert_eq!(cut.fragments(p), &want[..], "pixel {p}");
    }
    let mut t = FrontTracker::new(&cut);
    t.remove(3, |_, _, _| {});
    assert_eq!(t.count_of(7), 7 * 14);
    // Keeping everything is the identity.
    assert_eq!(ab.retain(|_, _| true), ab);
}

#[test]
fn alpha_test_discards_transparent_texels() {
    // Texture: left half transparent, right half opaque. Quad uvs span the texture.
    let tex = Texture::new(2, 1, &[[0, 0, 0, 0], [255, 255, 255, 255]]).unwrap();
    let mut tex = tex;
    tex.filter = Filter::Nearest;
    let mats = vec![RasterMaterial {
        texture: Some(0),
        ..RasterMaterial::default()
    }];
    let p = |x: f32, y: f32| pix(x, y, 0.0, W, H);
    let mut mesh = RasterMesh {
        positions: vec![p(0.0, 0.0), p(16.0, 0.0), p(16.0, 16.0), p(0.0, 16.0)],
        uvs: vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]],
        indices: vec![0, 1, 2, 0, 2, 3],
        item_of_triangle: vec![5, 5],
        ..RasterMesh::default()
    };
    let textures = [tex];
    let scene = Scene::single(&mesh, &mats, &textures);
    let f = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
    for y in 0..H {
        for x in 0..W {
            let k = (y * W + x) as usize;
            assert_eq!(f.item[k] == 5, x >= 8, "pixel {x},{y}");
            assert_eq!(f.color[k][3] == 255, x >= 8);
        }
    }
    let ab = ABuffer::render(&scene, &pixel_camera(W, H), W, H).unwrap();
    assert_eq!(ab.fragment_count(), (W * H / 2) as usize);
    // Without a cutoff nothing is discarded.
    let mats0 = vec![RasterMaterial {
        alpha_cutoff: 0.0,
        ..mats[0]
    }];
    mesh.material_of_triangle = vec![0, 0];
    let scene = Scene::single(&mesh, &mats0, &textures);
    let f = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
    assert!(f.item.iter().all(|&i| i == 5));
}

#[test]
fn complementary_screen_door_coverage_covers_each_pixel_once() {
    // Two coplanar quads over the whole image, items 1 and 2, coverage [0, w) and [w, 1): every
    // pixel is covered by exactly one, item 1 on a w share of each 4 × 4 block.
    let p = |x: f32, y: f32| pix(x, y, 0.0, W, H);
    let quad = [p(0.0, 0.0), p(W as f32, 0.0), p(W as f32, H as f32), p(0.0, H as f32)];
    let mut mesh = mesh_of(
        &[
            [quad[0], quad[1], quad[2]],
            [quad[0], quad[2], quad[3]],
            [quad[0], quad[1], quad[2]],
            [quad[0], quad[2], quad[3]],
        ],
        &[1, 1, 2, 2],
    );
    mesh.material_of_triangle = vec![0, 0, 1, 1];
    for w in [0.0, 0.25, 0.5, 0.8125, 1.0] {
        let mats = vec![
            RasterMaterial {
                coverage: [0.0, w],
                ..RasterMaterial::default()
            },
            RasterMaterial {
                coverage: [w, 1.0],
                ..RasterMaterial::default()
            },
        ];
        let scene = Scene::single(&mesh, &mats, &[]);
        let f = render(&scene, &pixel_camera(W, H), W, H, &RenderOptions::default()).unwrap();
        assert!(f.item.iter().all(|&i| i == 1 || i == 2), "w {w}: a pixel left empty");
        let ones = f.item.iter().filter(|&&i| i == 1).count();
        assert_eq!(ones as f32, w * (W * H) as f32, "w {w}");
        // The A-buffer applies the same test: one fragment per pixel.
        let ab = ABuffer::render(&scene, &pixel_camera(W, H), W, H).unwrap();
        assert_eq!(ab.fragment_count(), (W * H) as usize, "w {w}");
    }
}

#[test]
fn lighting_is_double_sided() {
    // A quad facing the camera and the sun; its mirror winding (back face) shades the same.
    let p = |x: f32, y: f32| pix(x, y, 0.0, W, H);
    let opts = RenderOptions {
        lighting: Lighting {
            sun_direction: Vec3::Z,
            sun: 1.0,
            ambient: 0.0,
        },
        ..RenderOptions::default()
    };
    let mats = vec![RasterMaterial {
        color: [0.5, 0.5, 0.5, 1.0],
        ..RasterMaterial::default()
    }];
    let front = mesh_of(&[[p(0.0, 0.0), p(0.0, 16.0), p(16.0, 0.0)]], &[]);
    let back = mesh_of(&[[p(0.0, 0.0), p(16.0, 0.0), p(0.0, 16.0)]], &[]);
    let cf = render(&Scene::single(&front, &mats, &[]), &pixel_camera(W, H), W, H, &opts).unwrap();
    let cb = render(&Scene::single(&back, &mats, &[]), &pixel_camera(W, H), W, H, &opts).unwrap();
    // Linear 0.5 → sRGB 188.
    assert_eq!(cf.color[0], [188, 188, 188, 255]);
    assert_eq!(cb.color[0], cf.color[0]);
    // Single-sided materials cull the back face.
    let single = vec![RasterMaterial {
        double_sided: false,
        ..mats[0]
    }];
    let cs = render(&Scene::single(&back, &single, &[]), &pixel_camera(W, H), W, H, &opts).unwrap();
    assert!(cs.item.iter().all(|&i| i == EMPTY_ITEM));
    assert_eq!(cs.color[0], [0; 4]);
}

/// A random cloud of textured leaf quads around the origin (radius ~1).
fn leaf_cloud(n: usize, seed: u64) -> crate::TreeModel {
    let mut s = seed;
    let mut rnd = move || {
        s = s
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        ((s >> 33) as f32) / (1u64 << 31) as f32 * 2.0 - 1.0
    };
    let leaves = (0..n)
        .map(|_| {
            let normal = Vec3::new(rnd(), rnd(), rnd()).normalize_or(Vec3::Z);
            let axis = normal.any_orthonormal_vector();
            crate::Leaf {
                center: Vec3::new(rnd(), rnd(), rnd()),
                normal,
                axis,
                width: 0.15,
                length: 0.25,
                branch: None,
                iteration: 0,
                material: 0,
            }
        })
        .collect();
    crate::TreeModel {
        name: "cloud".into(),
        branches: vec![crate::Branch {
            points: vec![
                crate::SkeletonPoint {
                    position: Vec3::new(0.0, -1.2, 0.0),
                    radius: 0.1,
                },
                crate::SkeletonPoint {
                    position: Vec3::new(0.0, 0.5, 0.0),
                    radius: 0.05,
                },
            ],
            parent: None,
            level: 1,
            iteration: 0,
        }],
        leaves,
        bark_mesh: crate::TriangleMesh::default(),
        materials: crate::Materials::default(),
        iterations: 0,
        source: crate::ModelSource::LSystem,
    }
}

#[test]
fn item_buffer_matches_abuffer_front_and_removal_reveals_behind() {
    let model = leaf_cloud(400, 7);
    let mesh = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    let textures = [Texture::procedural_leaf(16)];
    let mats = tree_materials(&model, &[Some(0)]);
    let scene = Scene::single(&mesh, &mats, &textures);
    for (k, cam) in [
        Camera::orbit_orthographic(Vec3::ZERO, 1.8, Vec3::new(1.0, 0.5, 0.3)),
        Camera::orbit_perspective(Vec3::ZERO, 1.8, Vec3::new(-0.2, 0.3, 1.0), 0.9),
    ]
    .iter()
    .enumerate()
    {
        let f = render(&scene, cam, 64, 48, &RenderOptions::default()).unwrap();
        let ab = ABuffer::render(&scene, cam, 64, 48).unwrap();
        let none = BitSet::new();
        let mut multi = 0;
        for p in 0..f.pixel_count() {
            assert_eq!(
                ab.front(p, &none).unwrap_or(EMPTY_ITEM),
                f.item[p],
                "view {k} pixel {p}"
            );
            if let Some(fr) = ab.fragments(p).first() {
                assert_eq!(fr.depth, f.depth[p]);
            }
            let fr = ab.fragments(p);
            assert!(
                fr.windows(2)
                    .all(|w| (w[0].depth, w[0].item) <= (w[1].depth, w[1].item))
            );
            multi += usize::from(fr.len() > 1);
        }
        assert!(multi > 100, "too little overlap to test: {multi}");
        assert!(f.item.contains(&BARK_ITEM) || k == 0);
        // Frame counts equal the A-buffer's front counts.
        let counts = ab.front_counts(&none);
        for (item, n) in f.item_pixel_counts() {
            assert_eq!(counts[ab.item_index(item).unwrap()], n);
        }
        // Remove front items one by one: the tracker agrees with a fresh resolve, and a pixel
        // fronted by a removed item shows the next fragment behind it.
        let mut tracker = FrontTracker::new(&ab);
        let mut removed = BitSet::new();
        let order: Vec<u32> = f
            .item_pixel_counts()
            .iter()
            .map(|x| x.0)
            .filter(|&i| i != BARK_ITEM)
            .take(60)
            .collect();
        for &item in &order {
            let before: Vec<Option<u32>> = (0..f.pixel_count()).map(|p| tracker.front(p)).collect();
            let mut changed = Vec::new();
            assert!(tracker.remove(item, |p, old, new| changed.push((p, old, new))));
            assert!(!tracker.remove(item, |_, _, _| {}));
            removed.insert(item);
            for &(p, old, new) in &changed {
                assert_eq!(old, item);
                assert_eq!(before[p as usize], Some(item));
                assert_eq!(new, ab.front(p as usize, &removed));
            }
            for (p, was) in before.iter().enumerate() {
                assert_eq!(tracker.front(p), ab.front(p, &removed));
                if *was == Some(item) {
                    let next = ab.fragments(p).iter().map(|fr| fr.item).find(|&i| !removed.contains(i));
                    assert_eq!(tracker.front(p), next);
                }
            }
            assert_eq!(tracker.count_of(item), 0);
        }
        assert_eq!(tracker.counts(), ab.front_counts(&removed).as_slice());
        assert_eq!(
            FrontTracker::with_removed(&ab, removed.clone()).counts(),
            tracker.counts()
        );
        assert!(ab.memory_bytes() > ab.fragment_count() * 8);
    }
}

#[test]
fn output_does_not_depend_on_thread_count() {
    let model = leaf_cloud(3000, 3);
    let mesh = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    let textures = [Texture::procedural_leaf(16)];
    let mats = tree_materials(&model, &[Some(0)]);
    let scene = Scene::single(&mesh, &mats, &textures);
    let cam = Camera::orbit_perspective(Vec3::ZERO, 1.8, Vec3::new(0.4, 0.2, 1.0), 0.8);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| {
            (
                render(&scene, &cam, 97, 75, &RenderOptions::default()).unwrap(),
                ABuffer::render(&scene, &cam, 97, 75).unwrap(),
            )
        })
    };
    let (f1, a1) = run(1);
    let (f4, a4) = run(4);
    assert!(f1.depth.iter().zip(&f4.depth).all(|(a, b)| a.to_bits() == b.to_bits()));
    assert_eq!(f1.item, f4.item);
    assert_eq!(f1.color, f4.color);
    assert_eq!(a1, a4);
}

#[test]
fn clipping_near_plane_and_huge_triangles() {
    let mats = opaque();
    // Looking down at 45° onto a huge ground triangle that extends behind the eye: it crosses
    // the near plane and the guard band, and must cover the whole image.
    let cam = Camera::look_at(
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, -1.0),
        Vec3::Y,
        Projection::Perspective {
            fov_y: 1.2,
            near: 0.1,
            far: 1e6,
        },
    );
    let big = [
        Vec3::new(-1e4, 0.0, 1e4),
        Vec3::new(1e4, 0.0, 1e4),
        Vec3::new(0.0, 0.0, -1e4),
    ];
    let f = render(
        &Scene::single(&mesh_of(&[big], &[]), &mats, &[]),
        &cam,
        33,
        21,
        &RenderOptions::default(),
    )
    .unwrap();
    assert!(f.item.iter().all(|&i| i == 0));
    assert!(f.depth.iter().all(|&d| (0.0..=1.0).contains(&d)));
    // Entirely behind the eye: nothing.
    let behind = [
        Vec3::new(-1.0, 0.0, 3.0),
        Vec3::new(1.0, 2.0, 3.0),
        Vec3::new(0.0, 1.0, 3.0),
    ];
    let f = render(
        &Scene::single(&mesh_of(&[behind], &[]), &mats, &[]),
        &cam,
        33,
        21,
        &RenderOptions::default(),
    )
    .unwrap();
    assert!(f.item.iter().all(|&i| i == EMPTY_ITEM));
    // Errors.
    let m = mesh_of(&[big], &[]);
    assert!(render(&Scene::single(&m, &mats, &[]), &cam, 0, 5, &RenderOptions::default()).is_err());
    let bad = RasterMesh {
        item_of_triangle: vec![],
        ..m.clone()
    };
    assert!(render(&Scene::single(&bad, &mats, &[]), &cam, 8, 8, &RenderOptions::default()).is_err());
    let texmats = vec![RasterMaterial {
        texture: Some(3),
        ..RasterMaterial::default()
    }];
    assert!(render(&Scene::single(&m, &texmats, &[]), &cam, 8, 8, &RenderOptions::default()).is_err());
}

#[test]
fn render_in_passes_equals_one_pass() {
    let model = leaf_cloud(400, 5);
    let textures = [Texture::procedural_leaf(8)];
    let mut mats = tree_materials(&model, &[Some(0)]);
    let mesh = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    // The same triangles in another colour: a full (depth, item) tie with `mesh`, where only
    // the tie-break by triangle order decides the colour.
    let mut recoloured = mesh.clone();
    let red = mats.len() as u16;
    mats.push(RasterMaterial {
        color: [1.0, 0.0, 0.0, 1.0],
        ..mats[mats.len() - 1]
    });
    recoloured.material_of_triangle.iter_mut().for_each(|m| *m = red);
    let at = |x: f32, z: f32, s: f32| Mat4::from_translation(Vec3::new(x, 0.0, z)) * Mat4::from_scale(Vec3::splat(s));
    let instances = vec![
        Instance {
            mesh: &mesh,
            transform: at(-0.6, 0.0, 0.5),
            items: ItemMap::Offset(0),
        },
        Instance {
            mesh: &mesh,
            transform: at(0.4, -0.5, 0.6),
            items: ItemMap::Offset(1000),
        },
        Instance {
            mesh: &recoloured,
            transform: at(-0.6, 0.0, 0.5),
            items: ItemMap::Offset(0),
        },
        Instance {
            mesh: &mesh,
            transform: at(0.0, 0.3, 0.7),
            items: ItemMap::Constant(7),
        },
        Instance {
            mesh: &recoloured,
            transform: at(0.4, -0.5, 0.6),
            items: ItemMap::Offset(1000),
        },
    ];
    let cam = Camera::orbit_perspective(Vec3::ZERO, 2.0, Vec3::new(0.3, 0.2, 1.0), 0.9);
    for order in [instances.clone(), instances.iter().rev().copied().collect()] {
        let scene = Scene {
            instances: order,
            materials: &mats,
            textures: &textures,
        };
        let one = render(&scene, &cam, 80, 64, &RenderOptions::default()).unwrap();
        let per_instance = mesh.triangle_count();
        for max in [1, per_instance, 2 * per_instance, 3 * per_instance - 1, usize::MAX] {
            let passes = render_in_passes(&scene, &cam, 80, 64, &RenderOptions::default(), max).unwrap();
            assert!(
                one.depth
                    .iter()
                    .zip(&passes.depth)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "depth differs at max {max}"
            );
            assert_eq!(one.item, passes.item, "items differ at max {max}");
            assert_eq!(one.color, passes.color, "colours differ at max {max}");
        }
        // The ties are there: the first of each tied pair decides the colour.
        let first_is_red = scene.instances[0].mesh.material_of_triangle[0] == red;
        let red_px = one.color.iter().filter(|c| c[0] > 0 && c[1] == 0 && c[2] == 0).count();
        assert_eq!(red_px > 0, first_is_red, "{red_px} red pixels");
    }
}

#[test]
fn instances_and_tree_subsets() {
    let model = leaf_cloud(50, 11);
    let textures = [Texture::procedural_leaf(8)];
    let mats = tree_materials(&model, &[Some(0)]);
    let full = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    let subset: Vec<u32> = (0..50).step_by(2).collect();
    let half = RasterMesh::from_tree(
        &model,
        &TreeMeshOptions {
            leaf_subset: Some(&subset),
            bark: false,
            leaf_scale: 1.5,
            ..TreeMeshOptions::default()
        },
    );
    assert_eq!(half.triangle_count(), 50);
    assert!(half.item_of_triangle.iter().all(|&i| i % 2 == 0));
    let cam = Camera::orbit_orthographic(Vec3::ZERO, 1.8, Vec3::Z);
    let f = render(
        &Scene::single(&half, &mats, &textures),
        &cam,
        64,
        64,
        &RenderOptions::default(),
    )
    .unwrap();
    assert!(f.item.iter().all(|&i| i == EMPTY_ITEM || i % 2 == 0));
    // Two instances side by side, items replaced by the instance number.
    let scene = Scene {
        instances: vec![
            Instance {
                mesh: &full,
                transform: Mat4::from_translation(Vec3::new(-1.0, 0.0, 0.0)) * Mat4::from_scale(Vec3::splat(0.4)),
                items: ItemMap::Constant(0),
            },
            Instance {
                mesh: &full,
                transform: Mat4::from_translation(Vec3::new(1.0, 0.0, 0.0)) * Mat4::from_scale(Vec3::splat(0.4)),
                items: ItemMap::Constant(1),
            },
        ],
        materials: &mats,
        textures: &textures,
    };
    let f = render(&scene, &cam, 64, 64, &RenderOptions::default()).unwrap();
    for y in 0..64 {
        for x in 0..64 {
            let i = f.item[y * 64 + x];
            if i != EMPTY_ITEM {
                assert_eq!(i, u32::from(x >= 32), "pixel {x},{y}");
            }
        }
    }
    assert!(f.item.contains(&0) && f.item.contains(&1));
    assert_eq!(ItemMap::Offset(10).apply(5), 15);
    assert_eq!(ItemMap::Offset(10).apply(BARK_ITEM), BARK_ITEM);
}

#[test]
fn metrics_on_rendered_frames() {
    let model = leaf_cloud(300, 5);
    let textures = [Texture::procedural_leaf(16)];
    let mats = tree_materials(&model, &[Some(0)]);
    let full = RasterMesh::from_tree(&model, &TreeMeshOptions::default());
    let cam = Camera::orbit_orthographic(Vec3::ZERO, 1.8, Vec3::new(0.2, 0.3, 1.0));
    let f = render(
        &Scene::single(&full, &mats, &textures),
        &cam,
        64,
        64,
        &RenderOptions::default(),
    )
    .unwrap();
    let c = crate::metrics::coverage(&f.coverage(), &f.coverage()).unwrap();
    assert_eq!((c.precision, c.recall), (1.0, 1.0));
    let s = crate::metrics::ssim_rgba(&f.color, &f.color, 64, 64, [0, 0, 0]).unwrap();
    assert!((s - 1.0).abs() < 1e-9);
    assert_eq!(crate::metrics::mask_from_alpha(&f.color), f.coverage());
    // Dropping half the leaves keeps precision high and lowers recall.
    let subset: Vec<u32> = (0..300).step_by(2).collect();
    let half = RasterMesh::from_tree(
        &model,
        &TreeMeshOptions {
            leaf_subset: Some(&subset),
            ..TreeMeshOptions::default()
        },
    );
    let g = render(
        &Scene::single(&half, &mats, &textures),
        &cam,
        64,
        64,
        &RenderOptions::default(),
    )
    .unwrap();
    let c = crate::metrics::coverage(&f.coverage(), &g.coverage()).unwrap();
    assert_eq!(c.precision, 1.0);
    assert!(c.recall < 0.95 && c.recall > 0.3, "{c:?}");
    assert!(crate::metrics::ssim_rgba(&f.color, &g.color, 64, 64, [0, 0, 0]).unwrap() < 0.99);
}
