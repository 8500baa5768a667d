//! The simulated PLC program, run once per cycle while the PLC is in RUN.
//!
//! Variables are found by name in the loaded public file, so the memory
//! layout always comes from the public file, as on a real PLC.
//!
//! - `demo`: the user manual's chapter 6.1 program: `dat` := today (DATE),
//!   `tim` := time of day (TIME), `c := c + 0.001`, `sinus := SIN(c)`,
//!   `cosinus := COS(c)`, `positive := sinus > 0`, `text := 'Have a nice
//!   day'`. The clock is UTC (plus any offset set by SETTID).
//! - `idle`: no program.
//!
//! Independently of the program, every variable matching an `animate` mask
//! changes every cycle: integers ramp, reals follow a sine, BOOLs toggle,
//! STRINGs count, DATE/DT/TIME/TOD advance.
//!
//! A variable of a Modbus tag file is written through its codec (word
//! order, scale, TS48), so the program's values are the ones a client reads.

use plccoms_protocol::value::Value;
use plccoms_protocol::IecType;

use plccoms_plc::value_codec::Codec;
use plccoms_plc::{MemoryImage, Var};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ProgramKind {
    #[default]
    Demo,
    Idle,
}

impl std::str::FromStr for ProgramKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "demo" => Ok(ProgramKind::Demo),
            "idle" => Ok(ProgramKind::Idle),
            other => Err(format!("unknown program '{other}' (demo or idle)")),
        }
    }
}

/// `*` matches any run of bytes; case-insensitive (ASCII).
pub fn mask_matches(mask: &[u8], name: &[u8]) -> bool {
    let (mut m, mut n) = (0, 0);
    let (mut star, mut star_n) = (None, 0);
    while n < name.len() {
        if m < mask.len() && mask[m] == b'*' {
            star = Some(m);
            star_n = n;
            m += 1;
        } else if m < mask.len() && mask[m].eq_ignore_ascii_case(&name[n]) {
            m += 1;
            n += 1;
        } else if let Some(s) = star {
            m = s + 1;
            star_n += 1;
            n = star_n;
        } else {
            return false;
        }
    }
    mask[m..].iter().all(|&b| b == b'*')
}

/// Indexes of the demo program's variables in the variable list.
#[derive(Debug, Clone, Default)]
struct DemoSlots {
    dat: Option<usize>,
    tim: Option<usize>,
    c: Option<usize>,
    sinus: Option<usize>,
    cosinus: Option<usize>,
    positive: Option<usize>,
    text: Option<usize>,
}

#[derive(Debug, Clone)]
pub struct Program {
    kind: ProgramKind,
    vars: Vec<Var>,
    demo: DemoSlots,
    animated: Vec<usize>,
    masks: Vec<Vec<u8>>,
    cycle: u64,
    cycle_ms: u64,
    /// Fraction of the animated variables changed per second, in turn;
    /// `None`: all of them every cycle.
    rate: Option<f64>,
    /// Changes owed to the rate, carried between cycles (less than one).
    owed: f64,
    /// The next animated variable to change at a rate.
    cursor: usize,
    /// How often each variable was changed at a rate (by its index in
    /// `vars`): its next value. Kept across new masks, so a variable
    /// animated again goes on from where it stopped.
    counts: Vec<u64>,
    /// Variable changes made by the animation so far.
    changes: u64,
}

impl Program {
    pub fn new(kind: ProgramKind, vars: Vec<Var>, masks: &[String], cycle_ms: u64) -> Self {
        let find = |name: &str| {
            vars.iter()
                .position(|v| v.name.eq_ignore_ascii_case(name.as_bytes()))
        };
        let demo = DemoSlots {
            dat: find("dat"),
            tim: find("tim"),
            c: find("c"),
            sinus: find("sinus"),
            cosinus: find("cosinus"),
            positive: find("positive"),
            text: find("text"),
        };
        let masks: Vec<Vec<u8>> = masks.iter().map(|m| m.as_bytes().to_vec()).collect();
        let animated = (0..vars.len())
            .filter(|&i| masks.iter().any(|m| mask_matches(m, &vars[i].name)))
            .collect();
        Program {
            kind,
            vars,
            demo,
            animated,
            masks,
            cycle: 0,
            cycle_ms: cycle_ms.max(1),
            rate: None,
            owed: 0.0,
            cursor: 0,
            counts: Vec::new(),
            changes: 0,
        }
    }

    /// Changes only `fraction` (0.0..=1.0) of the animated variables per
    /// second, in turn, each to a value it did not hold before (integers
    /// count up, BOOLs toggle), so a reader can count the changes made
    /// ([`Program::changes`]); `None`: every animated variable every cycle.
    pub fn with_rate(mut self, fraction: Option<f64>) -> Self {
        self.rate = fraction.map(|f| if f.is_nan() { 0.0 } else { f.clamp(0.0, 1.0) });
        self.counts = vec![0; self.vars.len()];
        self
    }

    /// This program in place of `old`: the same rate, the changes counted on.
    pub fn replacing(self, old: &Program) -> Self {
        let mut program = self.with_rate(old.rate);
        program.changes = old.changes;
        if program.vars == old.vars && old.counts.len() == program.counts.len() {
            program.counts.clone_from(&old.counts);
        }
        program
    }

    pub fn rate(&self) -> Option<f64> {
        self.rate
    }

    /// Variable changes the animation made so far.
    pub fn changes(&self) -> u64 {
        self.changes
    }

    pub fn kind(&self) -> ProgramKind {
        self.kind
    }

    pub fn vars(&self) -> &[Var] {
        &self.vars
    }

    pub fn masks(&self) -> Vec<String> {
        self.masks
            .iter()
            .map(|m| String::from_utf8_lossy(m).into_owned())
            .collect()
    }

    /// Names of the variables the animation drives.
    pub fn animated(&self) -> impl Iterator<Item = &Var> {
        self.animated.iter().map(|&i| &self.vars[i])
    }

    /// The same variables and masks, another program.
    pub fn with_kind(&self, kind: ProgramKind) -> Program {
        Program {
            kind,
            ..self.clone()
        }
    }

    /// One PLC cycle; `now` is the PLC clock in seconds since 1970 (UTC).
    pub fn step(&mut self, image: &mut MemoryImage, now: f64) {
        self.cycle = self.cycle.wrapping_add(1);
        if self.kind == ProgramKind::Demo {
            self.demo_step(image, now);
        }
        let Some(rate) = self.rate else {
            for k in 0..self.animated.len() {
                let i = self.animated[k];
                animate(&self.vars[i], image, self.cycle, self.cycle_ms, now, k);
            }
            self.changes += self.animated.len() as u64;
            return;
        };
        let n = self.animated.len();
        if n == 0 {
            return;
        }
        self.owed += rate * n as f64 * self.cycle_ms as f64 / 1000.0;
        // At most each variable once a cycle: a second change in the same
        // cycle could never be seen by a reader.
        let due = (self.owed.floor() as usize).min(n);
        self.owed = (self.owed - due as f64).min(n as f64);
        for _ in 0..due {
            let k = self.cursor;
            self.cursor = (k + 1) % n;
            let i = self.animated[k];
            self.counts[i] += 1;
            animate(&self.vars[i], image, self.counts[i], self.cycle_ms, now, k);
        }
        self.changes += due as u64;
    }

    fn demo_step(&self, image: &mut MemoryImage, now: f64) {
        let var = |slot: Option<usize>| slot.map(|i| &self.vars[i]);
        let day = (now / 86_400.0).floor();
        if let Some(v) = var(self.demo.dat) {
            write_f64(image, v, day * 86_400.0);
        }
        if let Some(v) = var(self.demo.tim) {
            write_f64(image, v, ((now - day * 86_400.0) * 1000.0).floor());
        }
        let c = match var(self.demo.c) {
            Some(v) => {
                let c = read_f64(image, v).unwrap_or(0.0) + 0.001;
                write_f64(image, v, c);
                read_f64(image, v).unwrap_or(c)
            }
            None => self.cycle as f64 * 0.001,
        };
        let sinus = c.sin();
        if let Some(v) = var(self.demo.sinus) {
            write_f64(image, v, sinus);
        }
        if let Some(v) = var(self.demo.cosinus) {
            write_f64(image, v, c.cos());
        }
        if let Some(v) = var(self.demo.positive) {
            write_f64(image, v, if sinus > 0.0 { 1.0 } else { 0.0 });
        }
        if let Some(v) = var(self.demo.text) {
            write_text(image, v, b"Have a nice day");
        }
    }
}

fn animate(v: &Var, image: &mut MemoryImage, cycle: u64, cycle_ms: u64, now: f64, k: usize) {
    match v.ty {
        IecType::Bool => write_f64(image, v, (cycle % 2) as f64),
        IecType::Real | IecType::Lreal => write_f64(
            image,
            v,
            (cycle as f64 * 0.01 + k as f64 * 0.5).sin() * 100.0,
        ),
        IecType::String(_) => write_text(image, v, format!("count {cycle}").as_bytes()),
        IecType::Date => {
            let day = (now / 86_400.0).floor() + cycle as f64;
            write_f64(image, v, day * 86_400.0)
        }
        IecType::Dt => write_f64(image, v, now.floor() + cycle as f64),
        IecType::Time => write_bytes(
            image,
            v,
            &(cycle.wrapping_mul(cycle_ms) as u32).to_le_bytes(),
        ),
        IecType::Tod => {
            let ms = (now.rem_euclid(86_400.0) * 1000.0) as u64 + cycle.wrapping_mul(cycle_ms);
            write_bytes(image, v, &((ms % 86_400_000) as u32).to_le_bytes())
        }
        // Integers ramp through their whole range, wrapping.
        _ => {
            let bytes = cycle.to_le_bytes();
            write_bytes(image, v, &bytes[..v.ty.size().min(8)]);
        }
    }
}

/// The bytes of `v` in the image, if they lie inside it.
fn place<'a>(image: &'a mut MemoryImage, v: &Var) -> Option<&'a mut [u8]> {
    let area = image.area_mut(v.area);
    let start = v.offset as usize;
    let end = start.checked_add(v.codec.byte_len(v.ty) as usize)?;
    area.get_mut(start..end)
}

/// Whether `v` is laid out by a codec of its own (a Modbus tag) rather
/// than in Tecomat memory's little-endian form.
fn encoded(v: &Var) -> bool {
    v.codec != Codec::Native && v.bit.is_none()
}

/// Writes `value` through `v`'s codec; a value its raw type cannot hold
/// (a scaled tag) is left out.
fn write_value(image: &mut MemoryImage, v: &Var, value: &Value) {
    if let (Ok(bytes), Some(target)) = (v.codec.encode(v.ty, value), place(image, v)) {
        let n = bytes.len().min(target.len());
        target[..n].copy_from_slice(&bytes[..n]);
    }
}

/// Little-endian bytes of an integer of `v`'s type.
fn write_bytes(image: &mut MemoryImage, v: &Var, bytes: &[u8]) {
    if encoded(v) {
        let mut le = [0u8; 8];
        let n = bytes.len().min(8);
        le[..n].copy_from_slice(&bytes[..n]);
        let value = Value::decode(v.ty, &le[..v.ty.size().min(8)]);
        return write_value(image, v, &value);
    }
    if let Some(target) = place(image, v) {
        let n = bytes.len().min(target.len());
        target[..n].copy_from_slice(&bytes[..n]);
    }
}

fn write_text(image: &mut MemoryImage, v: &Var, text: &[u8]) {
    if encoded(v) {
        let cap = match v.ty {
            IecType::String(n) => usize::from(n),
            _ => 0,
        };
        return write_value(image, v, &Value::Str(text[..text.len().min(cap)].to_vec()));
    }
    if let Some(target) = place(image, v) {
        let n = text.len().min(target.len().saturating_sub(1));
        target[..n].copy_from_slice(&text[..n]);
        target[n..].fill(0);
    }
}

/// Reads a numeric variable as f64 (BOOL as 0/1).
pub fn read_f64(image: &mut MemoryImage, v: &Var) -> Option<f64> {
    let bit = v.bit;
    let ty = v.ty;
    if encoded(v) {
        let value = v.codec.decode(ty, place(image, v)?);
        return (!ty.is_string()).then(|| value.as_f64());
    }
    let b = place(image, v)?;
    let u = |n: usize| {
        let mut raw = [0u8; 8];
        raw[..n].copy_from_slice(&b[..n]);
        u64::from_le_bytes(raw)
    };
    Some(match ty {
        IecType::Bool => f64::from((b[0] >> bit.unwrap_or(0).min(7)) & 1),
        IecType::Real => f64::from(f32::from_le_bytes(b[..4].try_into().ok()?)),
        IecType::Lreal | IecType::Date | IecType::Dt => f64::from_le_bytes(b[..8].try_into().ok()?),
        IecType::Sint => f64::from(b[0] as i8),
        IecType::Int => f64::from(i16::from_le_bytes([b[0], b[1]])),
        IecType::Dint => f64::from(i32::from_le_bytes(b[..4].try_into().ok()?)),
        IecType::Lint => i64::from_le_bytes(b[..8].try_into().ok()?) as f64,
        IecType::String(_) => return None,
        _ => u(ty.size().min(8)) as f64,
    })
}

/// Writes a numeric variable from f64 (integers rounded and saturated, BOOL
/// set when non-zero, only its own bit).
pub fn write_f64(image: &mut MemoryImage, v: &Var, x: f64) {
    let bit = v.bit;
    let ty = v.ty;
    if encoded(v) {
        let value = match ty {
            IecType::Real => Value::Real(x as f32),
            IecType::Lreal => Value::LReal(x),
            IecType::Date | IecType::Dt => Value::Date(x),
            IecType::Time | IecType::Tod => Value::Time(x.round() as u32),
            IecType::Sint | IecType::Int | IecType::Dint | IecType::Lint => {
                Value::Signed(x.round() as i64)
            }
            IecType::String(_) => return,
            _ => Value::Unsigned(x.round() as u64),
        };
        return write_value(image, v, &value);
    }
    let Some(b) = place(image, v) else { return };
    match ty {
        IecType::Bool => {
            let mask = 1u8 << bit.unwrap_or(0).min(7);
            if x != 0.0 {
                b[0] |= mask;
            } else {
                b[0] &= !mask;
            }
        }
        IecType::Real => b.copy_from_slice(&(x as f32).to_le_bytes()),
        IecType::Lreal | IecType::Date | IecType::Dt => b.copy_from_slice(&x.to_le_bytes()),
        IecType::Sint => b.copy_from_slice(&(x.round() as i8).to_le_bytes()),
        IecType::Int => b.copy_from_slice(&(x.round() as i16).to_le_bytes()),
        IecType::Dint => b.copy_from_slice(&(x.round() as i32).to_le_bytes()),
        IecType::Lint => b.copy_from_slice(&(x.round() as i64).to_le_bytes()),
        IecType::Byte | IecType::Usint => b[0] = x.round() as u8,
        IecType::Word | IecType::Uint => b.copy_from_slice(&(x.round() as u16).to_le_bytes()),
        IecType::Dword | IecType::Udint | IecType::Time | IecType::Tod => {
            b.copy_from_slice(&(x.round() as u32).to_le_bytes())
        }
        IecType::Lword | IecType::Ulint => b.copy_from_slice(&(x.round() as u64).to_le_bytes()),
        IecType::String(_) => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plccoms_plc::MemoryMap;
    use plccoms_protocol::Area;

    fn var(name: &str, offset: u32, bit: Option<u8>, ty: IecType) -> Var {
        Var {
            name: name.as_bytes().into(),
            area: Area::R,
            offset,
            bit,
            ty,
            codec: Codec::Native,
            writable: true,
            info: None,
        }
    }

    #[test]
    fn masks() {
        assert!(mask_matches(b"*", b"anything"));
        assert!(mask_matches(b"TEP*", b"teplota"));
        assert!(mask_matches(b"*a*a*", b"banana"));
        assert!(!mask_matches(b"tep", b"teplota"));
        assert!(mask_matches(b"teplota", b"TEPLOTA"));
        assert!(!mask_matches(b"*x", b"teplota"));
    }

    #[test]
    fn demo_program_runs_on_the_pub_layout() {
        let vars = vec![
            var("DAT", 0, None, IecType::Date),
            var("tim", 8, None, IecType::Time),
            var("c", 16, None, IecType::Lreal),
            var("sinus", 24, None, IecType::Lreal),
            var("cosinus", 32, None, IecType::Lreal),
            var("positive", 40, Some(3), IecType::Bool),
            var("other", 40, Some(2), IecType::Bool),
            var("text", 41, None, IecType::String(80)),
        ];
        let mut image = MemoryImage::new(MemoryMap::FOXTROT);
        image.area_mut(Area::R)[40] = 0x04;
        let mut program = Program::new(ProgramKind::Demo, vars.clone(), &[], 10);
        let now = 1_710_510_330.5; // 2024-03-15 13:45:30.5
        for _ in 0..3 {
            program.step(&mut image, now);
        }
        let r = image.area(Area::R);
        assert_eq!(
            f64::from_le_bytes(r[0..8].try_into().unwrap()),
            1_710_460_800.0
        );
        assert_eq!(u32::from_le_bytes(r[8..12].try_into().unwrap()), 49_530_500);
        let c = f64::from_le_bytes(r[16..24].try_into().unwrap());
        assert!((c - 0.003).abs() < 1e-12);
        assert_eq!(f64::from_le_bytes(r[24..32].try_into().unwrap()), c.sin());
        assert_eq!(r[40], 0x0C, "positive set, neighbour bit kept");
        assert_eq!(&r[41..57], b"Have a nice day\0");
    }

    #[test]
    fn modbus_tags_are_written_through_their_codec() {
        use plccoms_plc::modbus::{tags, MAP};
        let file = tags::parse(
            b"name,type,table,address,bit,order\n\
              sinus,REAL,holding,0,,CDAB\ntext,STRING[16],holding,10\n\
              positive,BOOL,coil,3\ncount,DINT,input,4,,DCBA\n",
        );
        let vars: Vec<Var> = file.tags.iter().map(tags::Tag::var).collect();
        let mut image = MemoryImage::new(MAP);
        let mut program = Program::new(ProgramKind::Demo, vars.clone(), &["count".into()], 10);
        program.step(&mut image, 0.0);
        let r = image.area(Area::R);
        let sinus = f32::from_be_bytes([r[2], r[3], r[0], r[1]]);
        assert_eq!(sinus, (0.001f64).sin() as f32);
        assert_eq!(&r[20..36], b"Have a nice day\0");
        assert_eq!(image.area(Area::Y)[3], 1, "sinus > 0");
        let input = plccoms_plc::modbus::INPUT_BASE as usize + 8;
        assert_eq!(
            i32::from_le_bytes(r[input..input + 4].try_into().unwrap()),
            1
        );
        assert_eq!(read_f64(&mut image, &vars[0]), Some(f64::from(sinus)));
    }

    #[test]
    fn animation_changes_every_cycle_and_stays_in_bounds() {
        let vars = vec![
            var("a_int", 0, None, IecType::Int),
            var("a_bool", 2, Some(1), IecType::Bool),
            var("a_real", 4, None, IecType::Real),
            var("a_str", 8, None, IecType::String(4)),
            var("edge", 512 * 1024 - 2, None, IecType::Dint),
            var("quiet", 20, None, IecType::Int),
        ];
        let mut image = MemoryImage::new(MemoryMap::FOXTROT);
        let mut program = Program::new(ProgramKind::Idle, vars, &["A_*".into(), "edge".into()], 10);
        program.step(&mut image, 0.0);
        let first = image.area(Area::R)[..24].to_vec();
        program.step(&mut image, 0.0);
        let second = image.area(Area::R)[..24].to_vec();
        assert_ne!(first[0..2], second[0..2]);
        assert_ne!(first[2], second[2]);
        assert_ne!(first[4..8], second[4..8]);
        assert_eq!(second[8..13], *b"coun\0");
        assert_eq!(second[20..22], [0, 0]);
    }

    #[test]
    fn a_change_rate_changes_that_share_in_turn() {
        let vars: Vec<Var> = (0..100)
            .map(|i| var(&format!("v{i}"), 2 * i, None, IecType::Int))
            .collect();
        let mut image = MemoryImage::new(MemoryMap::FOXTROT);
        // 10 % of 100 a second at 100 ms cycles: one variable a cycle.
        let mut program =
            Program::new(ProgramKind::Idle, vars, &["v*".into()], 100).with_rate(Some(0.1));
        let before = image.area(Area::R)[..200].to_vec();
        for _ in 0..10 {
            program.step(&mut image, 0.0);
        }
        let after = image.area(Area::R)[..200].to_vec();
        let changed = (0..100)
            .filter(|i| before[2 * i..2 * i + 2] != after[2 * i..2 * i + 2])
            .count();
        assert_eq!(changed, 10);
        assert_eq!(program.changes(), 10);
        assert_eq!(after[0..2], [1, 0]);
        // Around again: each variable counts on to a value it did not hold.
        for _ in 0..100 {
            program.step(&mut image, 0.0);
        }
        assert_eq!(program.changes(), 110);
        assert_eq!(image.area(Area::R)[0..2], [2, 0]);
        assert_eq!(image.area(Area::R)[20..22], [1, 0]);
        // Stopped and animated again: on from where each variable stood.
        let stopped =
            Program::new(ProgramKind::Idle, program.vars().to_vec(), &[], 100).replacing(&program);
        let mut again = Program::new(
            ProgramKind::Idle,
            stopped.vars().to_vec(),
            &["v*".into()],
            100,
        )
        .replacing(&stopped);
        again.step(&mut image, 0.0);
        assert_eq!(image.area(Area::R)[0..2], [3, 0]);
        assert_eq!(again.changes(), 111);
    }
}
