// Canopy viewer shaders. Colours are linear; the target is sRGB, so the hardware encodes.
// Lighting matches the shared CPU rasterizer: ambient + sun * max(n.l, 0), two-sided for leaves.

struct Globals {
    view_proj: mat4x4<f32>,
    // xyz: direction towards the sun (normalised), w: sun intensity.
    sun: vec4<f32>,
    // x: ambient, y: leaf alpha cutoff, z: billboard alpha cutoff, w: unused.
    params: vec4<f32>,
};

struct Tree {
    model: mat4x4<f32>,
    // rgb: debug colour, a: how much it replaces the material colour (0: none).
    tint: vec4<f32>,
};

struct Leaf {
    // xyz: centre (model space), w: colour as bitcast rgba8 (linear).
    center: vec4<f32>,
    // Half width along the blade's side.
    side: vec4<f32>,
    // Half length along the blade's axis.
    axis: vec4<f32>,
};

@group(0) @binding(0) var<uniform> globals: Globals;
@group(0) @binding(1) var<storage, read> trees: array<Tree>;
@group(0) @binding(2) var leaf_mask: texture_2d<f32>;
@group(0) @binding(3) var nearest: sampler;
@group(0) @binding(4) var billboards: texture_2d_array<f32>;
@group(0) @binding(5) var linear_clamp: sampler;

@group(1) @binding(0) var<storage, read> leaves: array<Leaf>;

fn lit(color: vec3<f32>, n: vec3<f32>) -> vec3<f32> {
    let light = globals.params.x + globals.sun.w * max(dot(n, globals.sun.xyz), 0.0);
    return color * light;
}

fn tinted(color: vec3<f32>, tint: vec4<f32>) -> vec3<f32> {
    return mix(color, tint.rgb, tint.a);
}

// ---- Leaves: one instance per drawn leaf, six vertices per quad. ----

struct LeafOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec3<f32>,
};

@vertex
fn leaf_vs(
    @builtin(vertex_index) vi: u32,
    @location(0) leaf_index: u32,
    @location(1) tree_index: u32,
    @location(2) scale: f32,
) -> LeafOut {
    // Corners (0,0) (1,0) (1,1) (0,0) (1,1) (0,1): the shared leaf_quads order.
    var us = array<f32, 6>(0.0, 1.0, 1.0, 0.0, 1.0, 0.0);
    var vs = array<f32, 6>(0.0, 0.0, 1.0, 0.0, 1.0, 1.0);
    let u = us[vi];
    let v = vs[vi];
    let leaf = leaves[leaf_index];
    let tree = trees[tree_index];
    let local = leaf.center.xyz + (leaf.side.xyz * (2.0 * u - 1.0) + leaf.axis.xyz * (2.0 * v - 1.0)) * scale;
    let n_local = normalize(cross(leaf.side.xyz, leaf.axis.xyz));
    var out: LeafOut;
    out.clip = globals.view_proj * tree.model * vec4<f32>(local, 1.0);
    out.uv = vec2<f32>(u, v);
    out.normal = normalize((tree.model * vec4<f32>(n_local, 0.0)).xyz);
    let rgba = unpack4x8unorm(bitcast<u32>(leaf.center.w));
    out.color = tinted(rgba.rgb, tree.tint);
    return out;
}

@fragment
fn leaf_fs(in: LeafOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    let mask = textureSample(leaf_mask, nearest, in.uv);
    if (mask.a < globals.params.y) {
        discard;
    }
    var n = normalize(in.normal);
    if (!front) {
        n = -n;
    }
    return vec4<f32>(lit(in.color * mask.rgb, n), 1.0);
}

// ---- Meshes (bark, hulls, ground): per-vertex colour, per-instance transform. ----

struct MeshOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) normal: vec3<f32>,
    @location(1) color: vec3<f32>,
};

@vertex
fn mesh_vs(
    @location(0) pos: vec3<f32>,
    @location(1) normal: vec3<f32>,
    @location(2) color: vec4<f32>,
    @location(3) m0: vec4<f32>,
    @location(4) m1: vec4<f32>,
    @location(5) m2: vec4<f32>,
    @location(6) m3: vec4<f32>,
    @location(7) tint: vec4<f32>,
) -> MeshOut {
    let model = mat4x4<f32>(m0, m1, m2, m3);
    var out: MeshOut;
    out.clip = globals.view_proj * model * vec4<f32>(pos, 1.0);
    out.normal = (model * vec4<f32>(normal, 0.0)).xyz;
    out.color = tinted(color.rgb, tint);
    return out;
}

@fragment
fn mesh_fs(in: MeshOut, @builtin(front_facing) front: bool) -> @location(0) vec4<f32> {
    var n = normalize(in.normal);
    if (!front) {
        n = -n;
    }
    return vec4<f32>(lit(in.color, n), 1.0);
}

// ---- Billboards: one quad per instance, up to three frames blended, unlit (baked lighting). ----

struct BillboardOut {
    @builtin(position) clip: vec4<f32>,
    @location(0) uv: vec2<f32>,
    @location(1) @interpolate(flat) layers: vec3<u32>,
    @location(2) weights: vec3<f32>,
    @location(3) tint: vec4<f32>,
    @location(4) @interpolate(flat) coverage: f32,
};

@vertex
fn billboard_vs(
    @builtin(vertex_index) vi: u32,
    @location(0) center: vec3<f32>,
    @location(1) right: vec3<f32>,
    @location(2) up: vec3<f32>,
    @location(3) layers: vec3<u32>,
    @location(4) weights: vec3<f32>,
    @location(5) tint: vec4<f32>,
    @location(6) coverage: f32,
) -> BillboardOut {
    // Top-left, top-right, bottom-right, top-left, bottom-right, bottom-left; uv row 0 at the top.
    var xs = array<f32, 6>(-1.0, 1.0, 1.0, -1.0, 1.0, -1.0);
    var ys = array<f32, 6>(1.0, 1.0, -1.0, 1.0, -1.0, -1.0);
    let x = xs[vi];
    let y = ys[vi];
    var out: BillboardOut;
    out.clip = globals.view_proj * vec4<f32>(center + right * x + up * y, 1.0);
    out.uv = vec2<f32>(0.5 * (x + 1.0), 0.5 * (1.0 - y));
    out.layers = layers;
    out.weights = weights;
    out.tint = tint;
    out.coverage = coverage;
    return out;
}

// 4 × 4 Bayer ordered-dither threshold in (0, 1) of a pixel.
fn dither(pixel: vec2<f32>) -> f32 {
    var bayer = array<f32, 16>(0.0, 8.0, 2.0, 10.0, 12.0, 4.0, 14.0, 6.0, 3.0, 11.0, 1.0, 9.0, 15.0, 7.0, 13.0, 5.0);
    let p = vec2<u32>(pixel) % vec2<u32>(4u, 4u);
    return (bayer[p.y * 4u + p.x] + 0.5) / 16.0;
}

@fragment
fn billboard_fs(in: BillboardOut) -> @location(0) vec4<f32> {
    // Cross-fade between billboard-cloud levels: complementary screen-door patterns.
    if (in.coverage < 1.0) {
        let t = dither(in.clip.xy);
        if ((in.coverage >= 0.0 && t >= in.coverage) || (in.coverage < 0.0 && t < 1.0 + in.coverage)) {
            discard;
        }
    }
    let a = textureSample(billboards, linear_clamp, in.uv, in.layers.x);
    let b = textureSample(billboards, linear_clamp, in.uv, in.layers.y);
    let c = textureSample(billboards, linear_clamp, in.uv, in.layers.z);
    let alpha = a.a * in.weights.x + b.a * in.weights.y + c.a * in.weights.z;
    if (alpha < globals.params.z) {
        discard;
    }
    let rgb = (a.rgb * a.a * in.weights.x + b.rgb * b.a * in.weights.y + c.rgb * c.a * in.weights.z) / alpha;
    return vec4<f32>(tinted(rgb, in.tint), 1.0);
}
