//! The scene graph: which meshes to import and their world transforms. Nodes are walked from the
//! chosen scene (default, else the first, else every root node), each node once; a node's world
//! transform is the product of the local transforms (matrix or TRS) along its parent chain.

use glam::{Mat4, Quat, Vec3};
use gltf::json;

use super::Importer;

impl Importer<'_, '_> {
    /// Meshes to import with their world transforms: `(node, mesh, world)`.
    pub(super) fn instances(&mut self) -> Vec<(Option<usize>, usize, Mat4)> {
        let root = self.root;
        let nodes = &root.nodes;
        let n = nodes.len();
        let mut parent: Vec<Option<usize>> = vec![None; n];
        for (i, node) in nodes.iter().enumerate() {
            for c in node.children.iter().flatten() {
                let c = c.value();
                if c >= n || c == i {
                    self.warnings
                        .push(format!("node {i} has an invalid child {c}; ignored"));
                } else if parent[c].is_none() {
                    parent[c] = Some(i);
                } else {
                    self.warnings
                        .push(format!("node {c} has more than one parent; using the first"));
                }
            }
        }
        let scene_nodes: Vec<usize> = match self.root.scene.map(|s| s.value()) {
            Some(s) if s < self.root.scenes.len() => self.root.scenes[s].nodes.iter().map(json::Index::value).collect(),
            other => {
                if let Some(s) = other {
                    self.warnings.push(format!("default scene {s} does not exist"));
                }
                if let Some(first) = self.root.scenes.first() {
                    if other.is_none() {
                        self.warnings.push("no default scene; using scene 0".into());
                    }
                    first.nodes.iter().map(json::Index::value).collect()
                } else {
                    self.warnings.push("no scenes; using every root node".into());
                    (0..n).filter(|&i| parent[i].is_none()).collect()
                }
            }
        };
        let mut out = Vec::new();
        let mut visited = vec![false; n];
        let mut cache: Vec<Option<Mat4>> = vec![None; n];
        let mut stack: Vec<usize> = Vec::new();
        for &s in scene_nodes.iter().rev() {
            if s < n {
                if parent[s].is_some() {
                    self.warnings
                        .push(format!("scene lists node {s}, which is not a root node; imported once"));
                }
                stack.push(s);
            } else {
                self.warnings
                    .push(format!("scene lists node {s}, which does not exist"));
            }
        }
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut visited[i], true) {
                continue;
            }
            let node = &nodes[i];
            if let Some(mesh) = node.mesh {
                if mesh.value() < self.root.meshes.len() {
                    let world = self.world_transform(i, &parent, &mut cache);
                    out.push((Some(i), mesh.value(), world));
                } else {
                    self.warnings.push(format!(
                        "node {i} refers to mesh {}, which does not exist; skipped",
                        mesh.value()
                    ));
                }
            }
            for c in node.children.iter().flatten().rev() {
                if c.value() < n && !visited[c.value()] {
                    stack.push(c.value());
                }
            }
        }
        if out.is_empty() && n == 0 && !self.root.meshes.is_empty() {
            self.warnings
                .push("no nodes; importing every mesh untransformed".into());
            out.extend((0..self.root.meshes.len()).map(|m| (None, m, Mat4::IDENTITY)));
        }
        out
    }

    fn local_transform(&mut self, i: usize) -> Mat4 {
        let root = self.root;
        let node = &root.nodes[i];
        if let Some(m) = node.matrix {
            return Mat4::from_cols_array(&m);
        }
        let t = node.translation.map_or(Vec3::ZERO, Vec3::from_array);
        let s = node.scale.map_or(Vec3::ONE, Vec3::from_array);
        let r = match node.rotation {
            None => Quat::IDENTITY,
            Some(json::scene::UnitQuaternion(q)) => {
                let q = Quat::from_array(q);
                let len = q.length();
                if len.is_finite() && len > 1e-6 {
                    q / len
                } else {
                    self.warnings
                        .push(format!("node {i} has a degenerate rotation; ignored"));
                    Quat::IDENTITY
                }
            }
        };
        Mat4::from_scale_rotation_translation(s, r, t)
    }

    /// World transform of node `i`: the product of the local transforms along its parent
    /// chain. Memoised in `cache` so that a whole hierarchy costs linear time; a cycle (invalid
    /// file) is cut after `parent.len()` steps.
    fn world_transform(&mut self, i: usize, parent: &[Option<usize>], cache: &mut [Option<Mat4>]) -> Mat4 {
        let mut chain = Vec::new();
        let mut cur = Some(i);
        let mut world = Mat4::IDENTITY;
        while let Some(c) = cur {
            if let Some(m) = cache[c] {
                world = m;
                break;
            }
            if chain.len() > parent.len() {
                self.warnings.push(format!("node hierarchy above node {i} has a cycle"));
                break;
            }
            chain.push(c);
            cur = parent[c];
        }
        for &k in chain.iter().rev() {
            world *= self.local_transform(k);
            cache[k] = Some(world);
        }
        world
    }
}
