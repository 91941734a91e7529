//! The per-plane table an export carries: for each frame (a plane of the export's `t`
//! axis) its session index, run, case and repeat, where the stages were commanded and
//! reported to be, the interferometer's reading and the exposure time. Columns, as
//! steps.csv names them (µm, seconds since the epoch); `None` where the session has no
//! value (no interferometer reading, no piezo).

use crate::session::StepRow;
use serde::Serialize;

/// Every plane's values, a column per quantity (JSON: one array per key).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Planes {
    pub index: Vec<u32>,
    pub run: Vec<u32>,
    pub case: Vec<String>,
    pub repeat: Vec<u32>,
    /// Commanded position on the job's stage (steps.csv `position_um`).
    pub position_um: Vec<f64>,
    /// The controller's reported position on the job's stage.
    pub axis_um: Vec<f64>,
    pub interferometer_um: Vec<Option<f64>>,
    pub piezo_commanded_um: Vec<Option<f64>>,
    pub piezo_um: Vec<Option<f64>>,
    /// Exposure time of the frame.
    pub t_unix_s: Vec<f64>,
}

/// The columns of [`Planes::csv`], in order.
pub const CSV_HEADER: &str =
    "index,run,case,repeat,position_um,axis_um,interferometer_um,piezo_commanded_um,piezo_um,t_unix_s";

impl Planes {
    pub fn from_steps(steps: &[StepRow]) -> Planes {
        let mut p = Planes::default();
        for s in steps {
            p.index.push(s.index);
            p.run.push(s.run);
            p.case.push(s.case.clone());
            p.repeat.push(s.repeat);
            p.position_um.push(s.position_um);
            p.axis_um.push(s.axis_um);
            p.interferometer_um.push(s.interferometer_um);
            p.piezo_commanded_um.push(s.piezo_commanded_um);
            p.piezo_um.push(s.piezo_um);
            p.t_unix_s.push(s.t_unix_s);
        }
        p
    }

    pub fn len(&self) -> usize {
        self.index.len()
    }

    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }

    /// Whether any plane has a piezo position (a plan that moves the piezo besides the axis).
    pub fn has_piezo(&self) -> bool {
        self.piezo_commanded_um.iter().any(Option::is_some)
    }

    /// Seconds from the first plane's exposure to plane `t`'s.
    pub fn delta_t_s(&self, t: usize) -> f64 {
        self.t_unix_s[t] - self.t_unix_s[0]
    }

    /// The table as CSV ([`CSV_HEADER`]; numbers in the shortest form that reads back to
    /// the same f64, empty where there is no value).
    pub fn csv(&self) -> String {
        let opt = |v: Option<f64>| v.map(|x| x.to_string()).unwrap_or_default();
        let mut w = csv::WriterBuilder::new().from_writer(Vec::new());
        // Writes to a Vec cannot fail.
        let _ = w.write_record(CSV_HEADER.split(','));
        for i in 0..self.len() {
            let _ = w.write_record([
                self.index[i].to_string(),
                self.run[i].to_string(),
                self.case[i].clone(),
                self.repeat[i].to_string(),
                self.position_um[i].to_string(),
                self.axis_um[i].to_string(),
                opt(self.interferometer_um[i]),
                opt(self.piezo_commanded_um[i]),
                opt(self.piezo_um[i]),
                self.t_unix_s[i].to_string(),
            ]);
        }
        String::from_utf8(w.into_inner().unwrap_or_default()).unwrap_or_default()
    }
}
