//! The viewer's wgpu renderer: pipelines, offscreen targets and read-back.
//!
//! Three pipelines share one bind group of globals (camera, lighting), per-frame tree transforms
//! and textures:
//! - **leaves**: one instance per drawn leaf (`LeafDraw`: leaf index into the model's leaf
//!   storage buffer, tree index, seed 004 enlargement), six vertices expanded in the shader,
//!   alpha-tested against the leaf mask, lit on both sides;
//! - **meshes**: bark tubes, crown hulls and the ground, per-vertex colour, one `MeshInstance`
//!   (transform and debug tint) per tree;
//! - **billboards**: one quad per instance blending up to three frames of a texture array
//!   (seed 001's hemi-octahedral blend; one frame for lat-long and crossed quads), unlit since
//!   the bake lit the images.
//!
//! Rendering goes to an offscreen colour texture (sRGB) with a depth buffer, used both by the
//! window (shown as an egui image) and by `--screenshot` (read back to a PNG), so the two paths
//! draw the same pixels.

use bytemuck::{Pod, Zeroable};
use glam::{Mat4, Vec3};
use wgpu::util::DeviceExt;

/// Colour target format (sRGB: shaders write linear colour).
pub const COLOR_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Rgba8UnormSrgb;
/// Depth format.
pub const DEPTH_FORMAT: wgpu::TextureFormat = wgpu::TextureFormat::Depth32Float;
/// Side of one billboard texture slot, texels (images of other sizes are resampled).
pub const BILLBOARD_SLOT: u32 = 128;
/// Billboard texture slots (array layers); the least recently drawn is reused.
pub const BILLBOARD_LAYERS: u32 = 256;
/// Leaf draws per instance buffer (64 MiB: under every adapter's 256 MiB buffer limit; a
/// full-detail forest draws tens of millions of leaves).
pub const LEAF_DRAWS_PER_BUFFER: usize = 4 << 20;
/// Leaf mask side, texels (the shared rasterizer's procedural leaf).
pub const LEAF_MASK_SIDE: u32 = 32;
/// Alpha cutoff of leaves (the shared rasterizer's leaf materials).
pub const LEAF_ALPHA_CUTOFF: f32 = 0.5;
/// Alpha cutoff of blended billboards.
pub const BILLBOARD_ALPHA_CUTOFF: f32 = 0.5;

/// Why the GPU path failed.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter (no Vulkan or GL driver).
    #[error("no GPU adapter: {0}")]
    NoAdapter(String),
    /// The device could not be created.
    #[error("GPU device: {0}")]
    Device(String),
    /// Read-back failed.
    #[error("read-back: {0}")]
    Readback(String),
}

/// Globals uniform.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct Globals {
    view_proj: [[f32; 4]; 4],
    sun: [f32; 4],
    params: [f32; 4],
}

/// Per-tree transform and debug tint (storage buffer, indexed by [`LeafDraw::tree`]).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct TreeTransform {
    /// Model → world.
    pub model: [[f32; 4]; 4],
    /// Debug colour (rgb) and how much it replaces the material (a).
    pub tint: [f32; 4],
}

/// One leaf as the shader reads it (model space).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct GpuLeaf {
    /// Centre (xyz) and the linear rgba8 colour bit-cast into w.
    pub center: [f32; 4],
    /// Half width along the blade's side.
    pub side: [f32; 4],
    /// Half length along the blade's axis.
    pub axis: [f32; 4],
}

/// One drawn leaf.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct LeafDraw {
    /// Index into the model's leaf buffer.
    pub leaf: u32,
    /// Index into the frame's tree transforms.
    pub tree: u32,
    /// Seed 004 enlargement (1: none).
    pub scale: f32,
    /// Padding.
    pub pad: u32,
}

/// Mesh vertex (model space, linear colour).
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct MeshVertex {
    /// Position.
    pub pos: [f32; 3],
    /// Normal.
    pub normal: [f32; 3],
    /// Linear RGBA.
    pub color: [f32; 4],
}

/// One instance of a mesh.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct MeshInstance {
    /// Model → world, columns.
    pub model: [[f32; 4]; 4],
    /// Debug tint.
    pub tint: [f32; 4],
}

/// One billboard quad.
#[repr(C)]
#[derive(Debug, Clone, Copy, Pod, Zeroable)]
pub struct BillboardInstance {
    /// Quad centre, world.
    pub center: [f32; 3],
    /// Half extent to the right, world.
    pub right: [f32; 3],
    /// Half extent upwards, world.
    pub up: [f32; 3],
    /// Texture array layers of up to three frames.
    pub layers: [u32; 3],
    /// Blend weights (sum 1; unused frames 0).
    pub weights: [f32; 3],
    /// Debug tint.
    pub tint: [f32; 4],
    /// Screen-door coverage of a cross-fade: `c > 0` keeps the pixels whose 4 × 4 ordered-dither
    /// threshold is below `c`, `c < 0` those at or above `1 + c` (the complement of `1 + c`), so
    /// two quads at `w` and `−(1 − w)` cover each pixel exactly once. 1 draws every pixel.
    pub coverage: f32,
}

/// A mesh uploaded once (bark variant, hull level, ground).
#[derive(Debug)]
pub struct GpuMesh {
    vertices: wgpu::Buffer,
    indices: wgpu::Buffer,
    index_count: u32,
}

impl GpuMesh {
    /// Uploads `vertices` and `indices` (triangles).
    pub fn new(device: &wgpu::Device, vertices: &[MeshVertex], indices: &[u32]) -> Self {
        let zero_v = [MeshVertex::zeroed()];
        let zero_i = [0u32; 3];
        let v = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh vertices"),
            contents: bytemuck::cast_slice(if vertices.is_empty() { &zero_v } else { vertices }),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let i = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("mesh indices"),
            contents: bytemuck::cast_slice(if indices.is_empty() { &zero_i } else { indices }),
            usage: wgpu::BufferUsages::INDEX,
        });
        Self {
            vertices: v,
            indices: i,
            index_count: if indices.is_empty() { 0 } else { indices.len() as u32 },
        }
    }

    /// Triangles.
    pub fn triangles(&self) -> u64 {
        u64::from(self.index_count / 3)
    }
}

/// A model's leaves on the GPU: a storage buffer and its bind group.
#[derive(Debug)]
pub struct LeafStore {
    buffer: wgpu::Buffer,
    bind_group: wgpu::BindGroup,
    capacity: u32,
}

impl LeafStore {
    /// Leaves it holds at most.
    pub fn capacity(&self) -> u32 {
        self.capacity
    }

    /// Writes `leaves` at index `at` (silently clipped to the capacity).
    pub fn write(&self, queue: &wgpu::Queue, at: u32, leaves: &[GpuLeaf]) {
        if at >= self.capacity || leaves.is_empty() {
            return;
        }
        let n = leaves.len().min((self.capacity - at) as usize);
        queue.write_buffer(
            &self.buffer,
            u64::from(at) * size_of::<GpuLeaf>() as u64,
            bytemuck::cast_slice(&leaves[..n]),
        );
    }
}

/// What one frame draws, ready for [`Renderer::render`].
#[derive(Debug, Default)]
pub struct FrameDraws<'a> {
    /// Identifies the instance data: [`Renderer::render`] uploads it once per generation and
    /// redraws it from any camera until the generation changes (0: always upload).
    pub generation: u64,
    /// Tree transforms (indexed by leaf draws).
    pub trees: &'a [TreeTransform],
    /// Leaf draws per model leaf store.
    pub leaves: Vec<(&'a LeafStore, &'a [LeafDraw])>,
    /// Mesh instances per mesh.
    pub meshes: Vec<(&'a GpuMesh, &'a [MeshInstance])>,
    /// Billboard quads.
    pub billboards: &'a [BillboardInstance],
}

/// Instance buffers of one generation.
#[derive(Debug)]
struct Uploaded {
    generation: u64,
    leaves: Vec<(wgpu::BindGroup, wgpu::Buffer, u32)>,
    meshes: Vec<(wgpu::Buffer, wgpu::Buffer, u32, wgpu::Buffer, u32)>,
    billboards: Option<(wgpu::Buffer, u32)>,
}

/// Camera and lighting of a frame.
#[derive(Debug, Clone, Copy)]
pub struct FrameCamera {
    /// View-projection (depth 0..1).
    pub view_proj: Mat4,
    /// Direction towards the sun.
    pub sun_direction: Vec3,
    /// Sun intensity.
    pub sun: f32,
    /// Ambient intensity.
    pub ambient: f32,
    /// Clear colour (sRGB bytes).
    pub clear: [u8; 3],
}

/// Offscreen colour and depth targets.
#[derive(Debug)]
pub struct Target {
    /// Colour texture ([`COLOR_FORMAT`]).
    pub color: wgpu::Texture,
    /// Its view.
    pub color_view: wgpu::TextureView,
    /// The same texels viewed as plain `Rgba8Unorm`: what egui samples (egui composites in
    /// gamma space, so it must read the sRGB bytes as they are).
    /// `None` for headless targets ([`Target::new`]): the view needs the adapter's
    /// `VIEW_FORMATS` downlevel flag, which GL adapters may lack, and only the window uses it.
    pub ui_view: Option<wgpu::TextureView>,
    depth_view: wgpu::TextureView,
    /// Size.
    pub size: (u32, u32),
}

impl Target {
    /// Headless targets of `width × height` (at least 1), without [`Target::ui_view`].
    pub fn new(device: &wgpu::Device, width: u32, height: u32) -> Self {
        Self::build(device, width, height, false)
    }

    /// Targets with [`Target::ui_view`], for a window. The device's adapter must support
    /// [`wgpu::DownlevelFlags::VIEW_FORMATS`] ([`supports_ui_view`]).
    pub fn with_ui_view(device: &wgpu::Device, width: u32, height: u32) -> Self {
        Self::build(device, width, height, true)
    }

    fn build(device: &wgpu::Device, width: u32, height: u32, ui: bool) -> Self {
        let size = wgpu::Extent3d {
            width: width.max(1),
            height: height.max(1),
            depth_or_array_layers: 1,
        };
        let color = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("colour target"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: COLOR_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT
                | wgpu::TextureUsages::COPY_SRC
                | wgpu::TextureUsages::TEXTURE_BINDING,
            view_formats: if ui { &[wgpu::TextureFormat::Rgba8Unorm] } else { &[] },
        });
        let depth = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("depth target"),
            size,
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: DEPTH_FORMAT,
            usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
            view_formats: &[],
        });
        Self {
            color_view: color.create_view(&wgpu::TextureViewDescriptor::default()),
            ui_view: ui.then(|| {
                color.create_view(&wgpu::TextureViewDescriptor {
                    format: Some(wgpu::TextureFormat::Rgba8Unorm),
                    ..wgpu::TextureViewDescriptor::default()
                })
            }),
            depth_view: depth.create_view(&wgpu::TextureViewDescriptor::default()),
            color,
            size: (size.width, size.height),
        }
    }
}

/// The renderer: pipelines and shared resources.
#[derive(Debug)]
pub struct Renderer {
    leaf_pipeline: wgpu::RenderPipeline,
    mesh_pipeline: wgpu::RenderPipeline,
    billboard_pipeline: wgpu::RenderPipeline,
    globals: wgpu::Buffer,
    trees: wgpu::Buffer,
    trees_capacity: u64,
    global_layout: wgpu::BindGroupLayout,
    leaf_layout: wgpu::BindGroupLayout,
    leaf_mask_view: wgpu::TextureView,
    billboard_texture: wgpu::Texture,
    billboard_view: wgpu::TextureView,
    nearest: wgpu::Sampler,
    linear: wgpu::Sampler,
    global_group: wgpu::BindGroup,
    dummy_leaves: LeafStore,
    uploaded: Option<Uploaded>,
}

fn vertex_attrs<const N: usize>(formats: [(u32, wgpu::VertexFormat); N]) -> Vec<wgpu::VertexAttribute> {
    let mut offset = 0;
    formats
        .iter()
        .map(|&(loc, f)| {
            let a = wgpu::VertexAttribute {
                format: f,
                offset,
                shader_location: loc,
            };
            offset += f.size();
            a
        })
        .collect()
}

/// An RGBA8 mask of the shared rasterizer's procedural leaf.
fn leaf_mask_rgba(side: u32) -> Vec<u8> {
    canopy_shared::raster::Texture::procedural_leaf_rgba(side)
        .into_iter()
        .flatten()
        .collect()
}

impl Renderer {
    /// Pipelines for `device`.
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Self {
        let shader = device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some("canopy shaders"),
            source: wgpu::ShaderSource::Wgsl(include_str!("shaders.wgsl").into()),
        });
        let vis_all = wgpu::ShaderStages::VERTEX | wgpu::ShaderStages::FRAGMENT;
        let global_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("globals"),
            entries: &[
                wgpu::BindGroupLayoutEntry {
                    binding: 0,
                    visibility: vis_all,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Uniform,
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 1,
                    visibility: wgpu::ShaderStages::VERTEX,
                    ty: wgpu::BindingType::Buffer {
                        ty: wgpu::BufferBindingType::Storage { read_only: true },
                        has_dynamic_offset: false,
                        min_binding_size: None,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 2,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 3,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 4,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Texture {
                        sample_type: wgpu::TextureSampleType::Float { filterable: true },
                        view_dimension: wgpu::TextureViewDimension::D2Array,
                        multisampled: false,
                    },
                    count: None,
                },
                wgpu::BindGroupLayoutEntry {
                    binding: 5,
                    visibility: wgpu::ShaderStages::FRAGMENT,
                    ty: wgpu::BindingType::Sampler(wgpu::SamplerBindingType::Filtering),
                    count: None,
                },
            ],
        });
        let leaf_layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
            label: Some("leaves"),
            entries: &[wgpu::BindGroupLayoutEntry {
                binding: 0,
                visibility: wgpu::ShaderStages::VERTEX,
                ty: wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                count: None,
            }],
        });
        let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
            label: Some("canopy"),
            bind_group_layouts: &[Some(&global_layout), Some(&leaf_layout)],
            immediate_size: 0,
        });
        let depth = || {
            Some(wgpu::DepthStencilState {
                format: DEPTH_FORMAT,
                depth_write_enabled: Some(true),
                depth_compare: Some(wgpu::CompareFunction::Less),
                stencil: wgpu::StencilState::default(),
                bias: wgpu::DepthBiasState::default(),
            })
        };
        let target = [Some(wgpu::ColorTargetState {
            format: COLOR_FORMAT,
            blend: None,
            write_mask: wgpu::ColorWrites::ALL,
        })];
        let primitive = wgpu::PrimitiveState {
            topology: wgpu::PrimitiveTopology::TriangleList,
            cull_mode: None,
            ..wgpu::PrimitiveState::default()
        };
        let pipeline = |label: &str, vs: &str, fs: &str, buffers: &[wgpu::VertexBufferLayout<'_>]| {
            let buffers: Vec<Option<wgpu::VertexBufferLayout<'_>>> = buffers.iter().cloned().map(Some).collect();
            device.create_render_pipeline(&wgpu::RenderPipelineDescriptor {
                label: Some(label),
                layout: Some(&layout),
                vertex: wgpu::VertexState {
                    module: &shader,
                    entry_point: Some(vs),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    buffers: &buffers,
                },
                primitive,
                depth_stencil: depth(),
                multisample: wgpu::MultisampleState::default(),
                fragment: Some(wgpu::FragmentState {
                    module: &shader,
                    entry_point: Some(fs),
                    compilation_options: wgpu::PipelineCompilationOptions::default(),
                    targets: &target,
                }),
                multiview_mask: None,
                cache: None,
            })
        };
        use wgpu::VertexFormat as F;
        let leaf_attrs = vertex_attrs([(0, F::Uint32), (1, F::Uint32), (2, F::Float32), (3, F::Uint32)]);
        let leaf_attrs = &leaf_attrs[..3];
        let leaf_pipeline = pipeline(
            "leaves",
            "leaf_vs",
            "leaf_fs",
            &[wgpu::VertexBufferLayout {
                array_stride: size_of::<LeafDraw>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: leaf_attrs,
            }],
        );
        let mesh_v = vertex_attrs([(0, F::Float32x3), (1, F::Float32x3), (2, F::Float32x4)]);
        let mesh_i = vertex_attrs([
            (3, F::Float32x4),
            (4, F::Float32x4),
            (5, F::Float32x4),
            (6, F::Float32x4),
            (7, F::Float32x4),
        ]);
        let mesh_pipeline = pipeline(
            "meshes",
            "mesh_vs",
            "mesh_fs",
            &[
                wgpu::VertexBufferLayout {
                    array_stride: size_of::<MeshVertex>() as u64,
                    step_mode: wgpu::VertexStepMode::Vertex,
                    attributes: &mesh_v,
                },
                wgpu::VertexBufferLayout {
                    array_stride: size_of::<MeshInstance>() as u64,
                    step_mode: wgpu::VertexStepMode::Instance,
                    attributes: &mesh_i,
                },
            ],
        );
        let bb_attrs = vertex_attrs([
            (0, F::Float32x3),
            (1, F::Float32x3),
            (2, F::Float32x3),
            (3, F::Uint32x3),
            (4, F::Float32x3),
            (5, F::Float32x4),
            (6, F::Float32),
        ]);
        let billboard_pipeline = pipeline(
            "billboards",
            "billboard_vs",
            "billboard_fs",
            &[wgpu::VertexBufferLayout {
                array_stride: size_of::<BillboardInstance>() as u64,
                step_mode: wgpu::VertexStepMode::Instance,
                attributes: &bb_attrs,
            }],
        );
        let globals = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("globals"),
            size: size_of::<Globals>() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let trees_capacity = 1024;
        let trees = Self::trees_buffer(device, trees_capacity);
        let mask = device.create_texture_with_data(
            queue,
            &wgpu::TextureDescriptor {
                label: Some("leaf mask"),
                size: wgpu::Extent3d {
                    width: LEAF_MASK_SIDE,
                    height: LEAF_MASK_SIDE,
                    depth_or_array_layers: 1,
                },
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING,
                view_formats: &[],
            },
            wgpu::util::TextureDataOrder::LayerMajor,
            &leaf_mask_rgba(LEAF_MASK_SIDE),
        );
        let leaf_mask_view = mask.create_view(&wgpu::TextureViewDescriptor::default());
        let billboard_texture = device.create_texture(&wgpu::TextureDescriptor {
            label: Some("billboard frames"),
            size: wgpu::Extent3d {
                width: BILLBOARD_SLOT,
                height: BILLBOARD_SLOT,
                depth_or_array_layers: BILLBOARD_LAYERS,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format: wgpu::TextureFormat::Rgba8UnormSrgb,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
            view_formats: &[],
        });
        let billboard_view = billboard_texture.create_view(&wgpu::TextureViewDescriptor {
            dimension: Some(wgpu::TextureViewDimension::D2Array),
            ..wgpu::TextureViewDescriptor::default()
        });
        let nearest = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("nearest"),
            ..wgpu::SamplerDescriptor::default()
        });
        let linear = device.create_sampler(&wgpu::SamplerDescriptor {
            label: Some("linear"),
            mag_filter: wgpu::FilterMode::Linear,
            min_filter: wgpu::FilterMode::Linear,
            ..wgpu::SamplerDescriptor::default()
        });
        let global_group = Self::global_group(
            device,
            &global_layout,
            &globals,
            &trees,
            &leaf_mask_view,
            &nearest,
            &billboard_view,
            &linear,
        );
        let dummy_leaves = {
            let buffer = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("no leaves"),
                size: size_of::<GpuLeaf>() as u64,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            });
            let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("no leaves"),
                layout: &leaf_layout,
                entries: &[wgpu::BindGroupEntry {
                    binding: 0,
                    resource: buffer.as_entire_binding(),
                }],
            });
            LeafStore {
                buffer,
                bind_group,
                capacity: 1,
            }
        };
        Self {
            dummy_leaves,
            uploaded: None,
            leaf_pipeline,
            mesh_pipeline,
            billboard_pipeline,
            globals,
            trees,
            trees_capacity,
            global_layout,
            leaf_layout,
            leaf_mask_view,
            billboard_texture,
            billboard_view,
            nearest,
            linear,
            global_group,
        }
    }

    fn trees_buffer(device: &wgpu::Device, capacity: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("tree transforms"),
            size: capacity * size_of::<TreeTransform>() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    #[allow(clippy::too_many_arguments)]
    fn global_group(
        device: &wgpu::Device,
        layout: &wgpu::BindGroupLayout,
        globals: &wgpu::Buffer,
        trees: &wgpu::Buffer,
        mask: &wgpu::TextureView,
        nearest: &wgpu::Sampler,
        billboards: &wgpu::TextureView,
        linear: &wgpu::Sampler,
    ) -> wgpu::BindGroup {
        device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("globals"),
            layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: globals.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: trees.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: wgpu::BindingResource::TextureView(mask),
                },
                wgpu::BindGroupEntry {
                    binding: 3,
                    resource: wgpu::BindingResource::Sampler(nearest),
                },
                wgpu::BindGroupEntry {
                    binding: 4,
                    resource: wgpu::BindingResource::TextureView(billboards),
                },
                wgpu::BindGroupEntry {
                    binding: 5,
                    resource: wgpu::BindingResource::Sampler(linear),
                },
            ],
        })
    }

    /// A leaf store for `capacity` leaves (at least 1).
    pub fn leaf_store(&self, device: &wgpu::Device, capacity: u32) -> LeafStore {
        let capacity = capacity.max(1);
        let buffer = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("model leaves"),
            size: u64::from(capacity) * size_of::<GpuLeaf>() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let bind_group = device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("model leaves"),
            layout: &self.leaf_layout,
            entries: &[wgpu::BindGroupEntry {
                binding: 0,
                resource: buffer.as_entire_binding(),
            }],
        });
        LeafStore {
            buffer,
            bind_group,
            capacity,
        }
    }

    /// Writes one billboard image (sRGB RGBA, [`BILLBOARD_SLOT`] square) into `layer`.
    pub fn write_billboard(&self, queue: &wgpu::Queue, layer: u32, rgba: &[u8]) {
        if layer >= BILLBOARD_LAYERS || rgba.len() != (BILLBOARD_SLOT * BILLBOARD_SLOT * 4) as usize {
            return;
        }
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture: &self.billboard_texture,
                mip_level: 0,
                origin: wgpu::Origin3d { x: 0, y: 0, z: layer },
                aspect: wgpu::TextureAspect::All,
            },
            rgba,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(4 * BILLBOARD_SLOT),
                rows_per_image: Some(BILLBOARD_SLOT),
            },
            wgpu::Extent3d {
                width: BILLBOARD_SLOT,
                height: BILLBOARD_SLOT,
                depth_or_array_layers: 1,
            },
        );
    }

    /// Renders `draws` into `target`.
    pub fn render(
        &mut self,
        device: &wgpu::Device,
        queue: &wgpu::Queue,
        target: &Target,
        cam: &FrameCamera,
        draws: &FrameDraws<'_>,
    ) {
        let g = Globals {
            view_proj: cam.view_proj.to_cols_array_2d(),
            sun: {
                let d = cam.sun_direction.normalize_or_zero();
                [d.x, d.y, d.z, cam.sun]
            },
            params: [cam.ambient, LEAF_ALPHA_CUTOFF, BILLBOARD_ALPHA_CUTOFF, 0.0],
        };
        queue.write_buffer(&self.globals, 0, bytemuck::bytes_of(&g));
        let need = draws.trees.len().max(1) as u64;
        if need > self.trees_capacity {
            self.trees_capacity = need.next_power_of_two();
            self.trees = Self::trees_buffer(device, self.trees_capacity);
            self.global_group = Self::global_group(
                device,
                &self.global_layout,
                &self.globals,
                &self.trees,
                &self.leaf_mask_view,
                &self.nearest,
                &self.billboard_view,
                &self.linear,
            );
        }
        let fresh = draws.generation == 0 || self.uploaded.as_ref().is_none_or(|u| u.generation != draws.generation);
        if fresh {
            if !draws.trees.is_empty() {
                queue.write_buffer(&self.trees, 0, bytemuck::cast_slice(draws.trees));
            }
            let init = |label: &str, contents: &[u8]| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some(label),
                    contents,
                    usage: wgpu::BufferUsages::VERTEX,
                })
            };
            self.uploaded = Some(Uploaded {
                generation: draws.generation,
                leaves: draws
                    .leaves
                    .iter()
                    .flat_map(|(store, d)| d.chunks(LEAF_DRAWS_PER_BUFFER).map(move |c| (store, c)))
                    .filter(|(_, c)| !c.is_empty())
                    .map(|(store, c)| {
                        (
                            store.bind_group.clone(),
                            init("leaf draws", bytemuck::cast_slice(c)),
                            c.len() as u32,
                        )
                    })
                    .collect(),
                meshes: draws
                    .meshes
                    .iter()
                    .filter(|(m, i)| !i.is_empty() && m.index_count > 0)
                    .map(|(m, i)| {
                        (
                            m.vertices.clone(),
                            m.indices.clone(),
                            m.index_count,
                            init("mesh instances", bytemuck::cast_slice(i)),
                            i.len() as u32,
                        )
                    })
                    .collect(),
                billboards: (!draws.billboards.is_empty()).then(|| {
                    (
                        init("billboards", bytemuck::cast_slice(draws.billboards)),
                        draws.billboards.len() as u32,
                    )
                }),
            });
        }
        let Some(up) = &self.uploaded else { return };
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("frame") });
        {
            let [r, gr, b] = cam.clear.map(|c| srgb_to_linear(c) as f64);
            let mut pass = enc.begin_render_pass(&wgpu::RenderPassDescriptor {
                label: Some("scene"),
                color_attachments: &[Some(wgpu::RenderPassColorAttachment {
                    view: &target.color_view,
                    depth_slice: None,
                    resolve_target: None,
                    ops: wgpu::Operations {
                        load: wgpu::LoadOp::Clear(wgpu::Color { r, g: gr, b, a: 1.0 }),
                        store: wgpu::StoreOp::Store,
                    },
                })],
                depth_stencil_attachment: Some(wgpu::RenderPassDepthStencilAttachment {
                    view: &target.depth_view,
                    depth_ops: Some(wgpu::Operations {
                        load: wgpu::LoadOp::Clear(1.0),
                        store: wgpu::StoreOp::Discard,
                    }),
                    stencil_ops: None,
                }),
                timestamp_writes: None,
                occlusion_query_set: None,
                multiview_mask: None,
            });
            pass.set_bind_group(0, &self.global_group, &[]);
            // Group 1 must be bound for every pipeline; meshes and billboards do not read it.
            pass.set_bind_group(1, &self.dummy_leaves.bind_group, &[]);
            pass.set_pipeline(&self.mesh_pipeline);
            for (v, i, count, inst, n) in &up.meshes {
                pass.set_vertex_buffer(0, v.slice(..));
                pass.set_vertex_buffer(1, inst.slice(..));
                pass.set_index_buffer(i.slice(..), wgpu::IndexFormat::Uint32);
                pass.draw_indexed(0..*count, 0, 0..*n);
            }
            pass.set_pipeline(&self.leaf_pipeline);
            for (group, buf, n) in &up.leaves {
                pass.set_bind_group(1, group, &[]);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(0..6, 0..*n);
            }
            if let Some((buf, n)) = &up.billboards {
                pass.set_pipeline(&self.billboard_pipeline);
                pass.set_vertex_buffer(0, buf.slice(..));
                pass.draw(0..6, 0..*n);
            }
        }
        queue.submit([enc.finish()]);
    }

    /// Reads `target`'s colour back as tightly packed sRGB RGBA rows.
    pub fn read_back(device: &wgpu::Device, queue: &wgpu::Queue, target: &Target) -> Result<Vec<u8>, GpuError> {
        let (w, h) = target.size;
        let row = 4 * w;
        let padded = row.div_ceil(wgpu::COPY_BYTES_PER_ROW_ALIGNMENT) * wgpu::COPY_BYTES_PER_ROW_ALIGNMENT;
        let buf = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("read-back"),
            size: u64::from(padded) * u64::from(h),
            usage: wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::MAP_READ,
            mapped_at_creation: false,
        });
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
            label: Some("read-back"),
        });
        enc.copy_texture_to_buffer(
            wgpu::TexelCopyTextureInfo {
                texture: &target.color,
                mip_level: 0,
                origin: wgpu::Origin3d::ZERO,
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::TexelCopyBufferInfo {
                buffer: &buf,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(padded),
                    rows_per_image: Some(h),
                },
            },
            wgpu::Extent3d {
                width: w,
                height: h,
                depth_or_array_layers: 1,
            },
        );
        queue.submit([enc.finish()]);
        let slice = buf.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = slice
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let mut out = Vec::with_capacity((row * h) as usize);
        for y in 0..h as usize {
            let s = y * padded as usize;
            out.extend_from_slice(&data[s..s + row as usize]);
        }
        drop(data);
        buf.unmap();
        Ok(out)
    }
}

/// sRGB byte to linear.
pub fn srgb_to_linear(c: u8) -> f32 {
    let c = f32::from(c) / 255.0;
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// Whether `adapter` can give a window its [`Target::ui_view`] (an `Rgba8Unorm` view of the
/// sRGB colour target).
pub fn supports_ui_view(adapter: &wgpu::Adapter) -> bool {
    adapter
        .get_downlevel_capabilities()
        .flags
        .contains(wgpu::DownlevelFlags::VIEW_FORMATS)
}

/// A headless device: the first adapter wgpu offers (Vulkan or GL), no surface.
pub fn headless_device() -> Result<(wgpu::Device, wgpu::Queue, String), GpuError> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions::default()))
        .map_err(|e| GpuError::NoAdapter(e.to_string()))?;
    let info = adapter.get_info();
    let name = format!("{} ({:?}, {})", info.name, info.backend, info.driver);
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("canopy headless"),
        required_limits: wgpu::Limits::downlevel_defaults().using_resolution(adapter.limits()),
        ..wgpu::DeviceDescriptor::default()
    }))
    .map_err(|e| GpuError::Device(e.to_string()))?;
    Ok((device, queue, name))
}
