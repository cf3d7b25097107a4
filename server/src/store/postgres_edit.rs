//! The PostgreSQL store's edit path (a child of [`super`], which it shares the store's state
//! with): the scene's locks held across replicas, the version read and built from one snapshot
//! outside any lock, then committed only over the version it was built from (compare-and-swap,
//! retried), with the terrain the version stands on read or set in the same steps.

use std::sync::Arc;

use super::super::postgres_conn::announce;
use super::super::scenes::{EditBatch, Edited, Instance, Limits, Publish, StoreError, apply_batch};
use super::super::sqlite::{max_instances, now_unix};
use super::super::terrains::{self, TerrainChange};
use super::{
    CAS_ATTEMPTS, PostgresStore, SCENE_LOCKS, check_bytes, col, get_meta, insert_instances, insert_version,
    load_instances, lock, owner_lock, prune_where,
};

impl PostgresStore {
    /// [`Self::edit_locked`] under the scene's locks: this process's, and across replicas a
    /// transaction-scoped advisory lock held on its own connection for the whole edit, so that an
    /// edit without a base version never loses its compare-and-swap to another replica's; readers
    /// do not wait for it.
    pub(super) fn edit_held(
        &self,
        id: &str,
        batch: &EditBatch,
        limits: &Limits,
        publish: Publish<'_>,
        terrain: TerrainChange<'_>,
    ) -> Result<Edited, StoreError> {
        let scene_lock = self.scene_locks.get(id);
        let _one_writer = lock(&scene_lock);
        self.inner.with(|c| {
            let mut held = c.transaction()?;
            held.execute("SELECT pg_advisory_xact_lock($1, hashtext($2))", &[&SCENE_LOCKS, &id])?;
            let out = self.edit_locked(id, batch, limits, publish, terrain);
            held.commit()?;
            out
        })
    }

    /// [`SceneStore::edit`] with the scene's locks held, and with `terrain` given,
    /// [`SceneStore::set_terrain`]: the terrain the version stands on is read from the snapshot it
    /// builds on, or is the one given, written in the version's transaction.
    fn edit_locked(
        &self,
        id: &str,
        batch: &EditBatch,
        limits: &Limits,
        publish: Publish<'_>,
        terrain: TerrainChange<'_>,
    ) -> Result<Edited, StoreError> {
        let mut attempt = 0;
        loop {
            attempt += 1;
            let (mut meta, owner, next_id, incarnation, current, ground) = self.read(|tx| {
                let meta = get_meta(tx, id)?.ok_or_else(|| StoreError::NotFound(id.to_string()))?;
                let r = tx
                    .query_opt("SELECT owner, next_id, incarnation FROM scenes WHERE id = $1", &[&id])?
                    .ok_or_else(|| StoreError::NotFound(id.to_string()))?;
                let (owner, next_id): (String, i64) = (col(&r, 0)?, col(&r, 1)?);
                let incarnation = col::<i64>(&r, 2)? as u64;
                let ground = match terrain {
                    TerrainChange::Set(t) => t.map(Arc::from),
                    TerrainChange::Keep => terrains::postgres_get(tx, id)?.map(Arc::from),
                };
                let current = match self.recent.take(id, meta.version, incarnation) {
                    Some(list) => list,
                    None => Arc::new(load_instances(tx, id)?),
                };
                Ok((meta, owner, next_id as u32, incarnation, current, ground))
            })?;
            let (read_version, created) = (meta.version, incarnation);
            let keep = |list| self.recent.put(id, read_version, created, list);
            if let Some(expected) = batch.base_version
                && expected != meta.version
            {
                keep(current);
                return Err(StoreError::Conflict {
                    current: meta.version,
                    expected,
                });
            }
            let mut list = Arc::unwrap_or_clone(current);
            let (next_id, mut changes) = match apply_batch(&mut list, next_id, batch, max_instances(&owner, limits)) {
                Ok(applied) => applied,
                Err(e) => {
                    keep(Arc::new(list));
                    return Err(e);
                }
            };
            changes.base_version = Some(meta.version);
            changes.terrain = ground;
            let base = meta.version;
            meta.version += 1;
            meta.instance_count = list.len() as u64;
            let published = publish(&meta, &list, &changes)?;
            let now = now_unix();
            let committed = self.write(|tx| {
                owner_lock(tx, &owner)?;
                let at = tx.query_opt("SELECT version FROM scenes WHERE id = $1 FOR UPDATE", &[&id])?;
                let Some(at) = at.as_ref().map(|r| col::<i64>(r, 0)).transpose()? else {
                    return Err(StoreError::NotFound(id.to_string()));
                };
                if at as u64 != base {
                    return Ok(Err(at as u64));
                }
                if !batch.remove.is_empty() {
                    let ids: Vec<i64> = batch.remove.iter().map(|&r| i64::from(r)).collect();
                    tx.execute("DELETE FROM instances WHERE scene = $1 AND id = ANY($2)", &[&id, &ids])?;
                }
                if !batch.moves.is_empty() {
                    let moved: Vec<&Instance> = batch
                        .moves
                        .iter()
                        .filter_map(|m| list.binary_search_by_key(&m.id, |i| i.id).ok().map(|k| &list[k]))
                        .collect();
                    let column = |f: &dyn Fn(&Instance) -> f32| -> Vec<f64> { moved.iter().map(|i| f64::from(f(i))).collect() };
                    let ids: Vec<i64> = moved.iter().map(|i| i64::from(i.id)).collect();
                    tx.execute(
                        "UPDATE instances AS i SET x = u.x, y = u.y, z = u.z, rotation = u.r, scale = u.s \
                         FROM unnest($2::BIGINT[], $3::FLOAT8[], $4::FLOAT8[], $5::FLOAT8[], $6::FLOAT8[], $7::FLOAT8[]) \
                         AS u(id, x, y, z, r, s) WHERE i.scene = $1 AND i.id = u.id",
                        &[
                            &id,
                            &ids,
                            &column(&|i| i.position[0]),
                            &column(&|i| i.position[1]),
                            &column(&|i| i.position[2]),
                            &column(&|i| i.rotation),
                            &column(&|i| i.scale),
                        ],
                    )?;
                }
                insert_instances(tx, id, &list[list.len() - batch.add.len()..])?;
                tx.execute(
                    "UPDATE scenes SET version = $2, next_id = $3, instance_count = $4 WHERE id = $1 AND version = $5",
                    &[&id, &(meta.version as i64), &i64::from(next_id), &(list.len() as i64), &(base as i64)],
                )?;
                if let TerrainChange::Set(t) = terrain {
                    terrains::postgres_put(tx, id, t)?;
                }
                insert_version(tx, id, meta.version, &published, now)?;
                announce(tx, self.replica, id, Some(meta.version))?;
                let pruned = prune_where(tx, Some(id), limits, now)?;
                check_bytes(tx, &owner, limits)?;
                Ok(Ok(pruned))
            })?;
            match committed {
                Ok(pruned) => {
                    self.recent.put(id, meta.version, incarnation, Arc::new(list));
                    return Ok(Edited { meta, pruned });
                }
                // Another replica committed meanwhile: apply the batch again to its version.
                Err(current) => {
                    if batch.base_version.is_some() || attempt >= CAS_ATTEMPTS {
                        return Err(StoreError::Conflict {
                            current,
                            expected: base,
                        });
                    }
                }
            }
        }
    }
}
