//! Fuzzes the billboard-cloud section decoder: any input must decode or give an error, never
//! panic; a section that decodes whole must give the same table from its table prefix alone, and
//! every level's textures must pass their CRCs from the level's single range (`verify_level`).
#![no_main]

use canopy_shared::format::cloud::{CloudTable, decode_clouds};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(t) = decode_clouds(data) else {
        return;
    };
    if data.is_empty() {
        return;
    }
    let tl = CloudTable::peek_table_len(data).expect("a decoded section has a table length") as usize;
    let again = CloudTable::decode(&data[..tl], data.len() as u64).expect("the prefix decodes alone");
    assert_eq!(again, t);
    for k in 0..t.levels.len() {
        let r = t.level_range(k).expect("level in range");
        let level = &data[r.start as usize..r.end as usize];
        // Every texture passed its CRC in the whole section: the level's own check agrees.
        t.verify_level(k, level).expect("a level of a decoded section verifies");
        // PNG decoding may fail on fuzzed images; it must not panic.
        let _ = t.decode_level(k, level);
    }
});
