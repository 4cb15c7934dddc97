//! numpy loads our .npy files in one call (skipped when python3 + numpy
//! are not installed; the header and data layout are also checked in Rust
//! by the unit tests of `io::npy`).

use std::process::Command;

use ebptv_io::npy::{write_npy_f64, write_npy_table, NpyColumn, NpyEventWriter};
use ebptv_io::EventWriter;
use ebptv_io::{Chunk, Edge, Trigger};

fn numpy_available() -> bool {
    Command::new("python3")
        .args(["-c", "import numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false)
}

#[ebptv_macros::unit_test]
fn numpy_loads_events_tables_and_arrays() {
    if !numpy_available() {
        eprintln!("skip: python3 with numpy not available");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let ev = dir.path().join("ev.npy");
    let mut w: Box<dyn EventWriter> = Box::new(NpyEventWriter::create(&ev).unwrap());
    let mut c = Chunk::default();
    for i in 0..1000i64 {
        c.events.push(
            i * 3 - 100,
            (i % 1280) as u16,
            (i % 720) as u16,
            (i % 2) as u8,
        );
    }
    c.triggers.push(Trigger {
        t: 7,
        channel: 1,
        edge: Edge::Rising,
    });
    w.write_chunk(&c).unwrap();
    w.finish().unwrap();
    let tab = dir.path().join("tab.npy");
    write_npy_table(
        &tab,
        &[
            ("x", NpyColumn::F64(&[0.5, 1.5])),
            ("n", NpyColumn::U32(&[3, 4])),
        ],
    )
    .unwrap();
    let arr = dir.path().join("arr.npy");
    write_npy_f64(&arr, &[2, 3], &[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]).unwrap();
    let script = format!(
        "import numpy as np\n\
         e = np.load(r'{}')\n\
         assert e.shape == (1000,) and e.dtype.names == ('t','x','y','p'), (e.shape, e.dtype)\n\
         assert e['t'][0] == -100 and e['t'][-1] == 2897 and e['x'][999] == 999 and e['p'].sum() == 500\n\
         tr = np.load(r'{}')\n\
         assert tr.shape == (1,) and tr['t'][0] == 7 and tr['id'][0] == 1 and tr['p'][0] == 1\n\
         t = np.load(r'{}')\n\
         assert list(t['x']) == [0.5, 1.5] and list(t['n']) == [3, 4]\n\
         a = np.load(r'{}')\n\
         assert a.shape == (2, 3) and a[1, 2] == 5.0\n",
        ev.display(),
        dir.path().join("ev_triggers.npy").display(),
        tab.display(),
        arr.display()
    );
    let out = Command::new("python3")
        .args(["-c", &script])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
