//! Fuzzes the `.ctree` decoder: any input must decode or give an error, never panic, and a file
//! that decodes must re-open through the range reader with the same node table.
#![no_main]

use std::sync::Arc;

use canopy_shared::format::DecodedTree;
use canopy_shared::reader::{MemoryReader, open_tree};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let whole = DecodedTree::decode(data);
    let indexed = open_tree(&MemoryReader(Arc::from(data.to_vec())));
    if let Ok(t) = whole {
        let idx = indexed.expect("a file that decodes whole must open by range");
        assert_eq!(idx.nodes, t.nodes);
        let _ = t.to_model(0.5);
    }
});
