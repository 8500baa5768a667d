//! `GETFILEINFO:<name>`: `GETFILEINFO:<name>[<len>]=<size> <attr> <created>
//! <modified>`, `len` being the length of the text after `=`. Attribute bits
//! and the `ttida` times as in `backend::FileInfo`. A missing file, a local
//! name leading outside the root folder, or one of the server's secret files,
//! is ERROR 40.

use plccoms_protocol::answer::ErrorCode;

use super::{error, is_local, local_path, trim, Cx, FileThen, Reply};
use plccoms_core::driver::FileInfo;
use plccoms_core::link::files::FileJob;
use plccoms_core::localfs::{self, Access};

pub fn run(cx: &mut Cx<'_>, args: &[u8], context: &[u8], out: &mut Vec<u8>) -> Reply {
    let name = trim(args);
    if name.is_empty() {
        return error(cx, ErrorCode::Incomplete, context, out);
    }
    if is_local(name) {
        let info = local_path(cx, name, Access::Read).and_then(|path| localfs::info(&path).ok());
        return match info {
            Some(info) => {
                write_info(out, name, &info, cx.client.eol);
                Reply::Done
            }
            None => error(cx, ErrorCode::FileInfo, name, out),
        };
    }
    let rx = cx.section.file(FileJob::Info {
        path: name.to_vec(),
    });
    let then = FileThen::Info {
        name: name.to_vec(),
    };
    Reply::file(rx, then)
}

pub fn write_info(out: &mut Vec<u8>, name: &[u8], info: &FileInfo, eol: &[u8]) {
    let text = format!(
        "{} {} {} {}",
        info.size, info.attributes, info.created, info.modified
    );
    super::write_block(out, b"GETFILEINFO", name, text.as_bytes(), eol);
}
