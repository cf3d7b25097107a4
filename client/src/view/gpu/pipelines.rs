//! The renderer's pipelines and shared resources: one bind group of globals (camera and
//! lighting uniform, per-frame tree transforms, leaf mask, billboard texture array and their
//! samplers), one of a model's leaves, and the leaf, mesh and billboard pipelines over
//! `shaders.wgsl`. Also the resources made on demand: leaf stores and billboard frames.

use wgpu::util::DeviceExt;

use super::buffers::{
    BillboardInstance, Globals, GpuLeaf, LeafDraw, LeafStore, MeshInstance, MeshVertex, TreeTransform,
};
use super::frame::Uploaded;
use super::{BILLBOARD_LAYERS, BILLBOARD_SLOT, COLOR_FORMAT, DEPTH_FORMAT, LEAF_MASK_SIDE};

/// The renderer: pipelines and shared resources.
#[derive(Debug)]
pub struct Renderer {
    pub(super) leaf_pipeline: wgpu::RenderPipeline,
    pub(super) mesh_pipeline: wgpu::RenderPipeline,
    pub(super) billboard_pipeline: wgpu::RenderPipeline,
    pub(super) globals: wgpu::Buffer,
    pub(super) trees: wgpu::Buffer,
    pub(super) trees_capacity: u64,
    pub(super) global_layout: wgpu::BindGroupLayout,
    pub(super) leaf_layout: wgpu::BindGroupLayout,
    pub(super) leaf_mask_view: wgpu::TextureView,
    pub(super) billboard_texture: wgpu::Texture,
    pub(super) billboard_view: wgpu::TextureView,
    pub(super) nearest: wgpu::Sampler,
    pub(super) linear: wgpu::Sampler,
    pub(super) global_group: wgpu::BindGroup,
    pub(super) dummy_leaves: LeafStore,
    pub(super) uploaded: Option<Uploaded>,
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

    pub(super) fn trees_buffer(device: &wgpu::Device, capacity: u64) -> wgpu::Buffer {
        device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("tree transforms"),
            size: capacity * size_of::<TreeTransform>() as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    #[allow(clippy::too_many_arguments)]
    pub(super) fn global_group(
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
}
