//! Fuzzes the `.ctree` decoder: any input must decode or give an error, never panic, and a file
//! that decodes whole must also open as a client opens it (header and directory from the first
//! request, then the node table) with the same node table.
#![no_main]

use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::tree::{decode_index, decode_node_index, section_bytes};
use canopy_shared::format::{DecodedTree, FIRST_REQUEST_LEN};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let whole = DecodedTree::decode(data);
    let first = &data[..data.len().min(FIRST_REQUEST_LEN as usize)];
    let indexed = decode_index(first, Some(data.len() as u64)).and_then(|(_, dir)| {
        // No node table: decode_node_index says so.
        let table = match dir.section(SectionKind::NodeTable) {
            Some(e) => section_bytes(data, e)?,
            None => &[],
        };
        decode_node_index(&dir, table)
    });
    if let Ok(t) = whole {
        let idx = indexed.expect("a file that decodes whole must open by range");
        assert_eq!(idx.nodes, t.nodes);
        let _ = t.to_model(0.5);
    }
});
