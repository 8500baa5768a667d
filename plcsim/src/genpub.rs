//! Generated public files for load tests and benchmarks: `ANIM_nnnnn`
//! (UDINT, for the simulator's `--animate 'ANIM_*'`: each holds the PLC
//! cycle counter), `SETV_nnn` (DINT, targets of SET) and `VAR_nnnnn` of
//! mixed types, packed in the R area, with a CRC trailer.

use std::fmt::Write as _;

/// How many variables of each kind a generated project has.
pub struct Layout {
    pub vars: usize,
    pub animated: usize,
    pub setvars: usize,
}

/// A project of `vars` VAR variables only (nothing animated, no SET
/// targets).
pub fn plain(vars: usize) -> Vec<u8> {
    generate(&Layout {
        vars,
        animated: 0,
        setvars: 0,
    })
}

/// The public file of `layout`: ANIM, then SETV, then VAR variables.
pub fn generate(layout: &Layout) -> Vec<u8> {
    let mut text = String::with_capacity(layout.vars * 40);
    let mut offset = 0usize;
    let mut n = 0usize;
    for i in 0..layout.animated.min(layout.vars) {
        let _ = writeln!(text, " ANIM_{i:05} R B {offset} UDINT PUB_INOUT");
        offset += 4;
        n += 1;
    }
    for i in 0..layout.setvars.min(layout.vars - n) {
        let _ = writeln!(text, " SETV_{i:03} R B {offset} DINT PUB_INOUT");
        offset += 4;
        n += 1;
    }
    let types = [
        "BOOL",
        "INT",
        "DINT",
        "UDINT",
        "REAL",
        "LREAL",
        "WORD",
        "STRING[16]",
    ];
    let sizes = [0usize, 2, 4, 4, 4, 8, 2, 17];
    let mut bit = 0u8;
    for i in 0..layout.vars - n {
        let k = i % types.len();
        if k == 0 {
            let _ = writeln!(text, " VAR_{i:05} R B {offset} .{bit} BOOL PUB_INOUT");
            bit += 1;
            if bit == 8 {
                bit = 0;
                offset += 1;
            }
            continue;
        }
        if bit != 0 {
            bit = 0;
            offset += 1;
        }
        let kind = if types[k].contains("REAL") { "F" } else { "B" };
        let _ = writeln!(text, " VAR_{i:05} R {kind} {offset} {} PUB_INOUT", types[k]);
        offset += sizes[k];
    }
    let mut bytes = text.into_bytes();
    let crc = plccoms_plc::pubfile::crc_of(plccoms_plc::pubfile::crc_content(&bytes));
    bytes.extend_from_slice(format!(";* Crc=\"{crc:08X}\"\n").as_bytes());
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::pubfile;

    #[test]
    fn a_generated_project_parses_cleanly_with_its_crc() {
        let bytes = generate(&Layout {
            vars: 1000,
            animated: 10,
            setvars: 5,
        });
        let file = pubfile::parse(&bytes);
        assert!(file.warnings.is_empty(), "{:?}", file.warnings);
        assert_eq!(file.vars.len(), 1000);
        assert_eq!(&file.vars[0].var.name[..], b"ANIM_00000");
        assert_eq!(&file.vars[10].var.name[..], b"SETV_000");
        assert_eq!(&file.vars[15].var.name[..], b"VAR_00000");
        assert_eq!(
            file.crc,
            Some(pubfile::crc_of(pubfile::crc_content(&bytes)))
        );
    }
}
