//! GRBL 1.1's error and alarm codes, typed, with the meaning GRBL documents for each
//! (grbl/doc/csv/error_codes_en_US.csv and alarm_codes_en_US.csv).

macro_rules! codes {
    ($(#[$m:meta])* $name:ident { $($var:ident = $code:literal : $text:literal,)* }) => {
        $(#[$m])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        pub enum $name {
            $($var,)*
            /// A code this table does not know (newer firmware, forks).
            Unknown(u32),
        }

        impl $name {
            pub fn from_code(code: u32) -> $name {
                match code {
                    $($code => $name::$var,)*
                    other => $name::Unknown(other),
                }
            }
            pub fn code(self) -> u32 {
                match self {
                    $($name::$var => $code,)*
                    $name::Unknown(c) => c,
                }
            }
            pub fn text(self) -> &'static str {
                match self {
                    $($name::$var => $text,)*
                    $name::Unknown(_) => "unknown code (not in GRBL 1.1's table)",
                }
            }
        }

        impl std::fmt::Display for $name {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "{} ({})", self.code(), self.text())
            }
        }
    };
}

codes! {
    /// `error:N` replies: the line was not executed.
    GrblErrorCode {
        ExpectedCommandLetter = 1: "Expected command letter: G-code words consist of a letter and a value, and the letter was not found",
        BadNumberFormat = 2: "Bad number format: a value is missing or not a valid number",
        InvalidStatement = 3: "Invalid statement: the '$' system command was not recognized or supported",
        NegativeValue = 4: "Value < 0: negative value received for an expected positive value",
        SettingDisabled = 5: "Setting disabled: homing cycle is not enabled via settings ($22)",
        StepPulseMin = 6: "Value < 3 usec: minimum step pulse time must be greater than 3 usec",
        EepromReadFail = 7: "EEPROM read fail: settings restored to defaults",
        NotIdle = 8: "Not idle: '$' command cannot be used unless Grbl is IDLE",
        GcodeLock = 9: "G-code lock: G-code is locked out during alarm or jog state",
        SoftLimitNoHoming = 10: "Homing not enabled: soft limits cannot be enabled without homing",
        LineOverflow = 11: "Line overflow: maximum line length exceeded",
        StepRateExceeded = 12: "Step rate > 30kHz: the setting exceeds the maximum step rate",
        CheckDoor = 13: "Check door: safety door detected as opened and door state initiated",
        LineLengthExceeded = 14: "Line length exceeded: build info or startup line exceeds EEPROM line length limit",
        TravelExceeded = 15: "Travel exceeded: jog target exceeds machine travel, command ignored",
        InvalidJog = 16: "Invalid jog command: jog command has no '=' or contains prohibited g-code",
        LaserModeNoPwm = 17: "Setting disabled: laser mode requires PWM output",
        UnsupportedCommand = 20: "Unsupported command: unsupported or invalid g-code command found in block",
        ModalGroupViolation = 21: "Modal group violation: more than one g-code command from the same modal group in the block",
        UndefinedFeedRate = 22: "Undefined feed rate: feed rate has not yet been set or is undefined",
        NotInteger = 23: "Invalid gcode ID:23: g-code command in block requires an integer value",
        AxisConflict = 24: "Invalid gcode ID:24: more than one g-code command that requires axis words found in block",
        WordRepeated = 25: "Invalid gcode ID:25: repeated g-code word found in block",
        NoAxisWords = 26: "Invalid gcode ID:26: no axis words found in block for a command that requires them",
        InvalidLineNumber = 27: "Invalid gcode ID:27: line number value is invalid",
        ValueWordMissing = 28: "Invalid gcode ID:28: g-code command is missing a required value word",
        UnsupportedCoordSys = 29: "Invalid gcode ID:29: G59.x work coordinate systems are not supported",
        G53InvalidMotion = 30: "Invalid gcode ID:30: G53 only allowed with G0 and G1 motion modes",
        AxisWordsExist = 31: "Invalid gcode ID:31: axis words found in block when no command or current modal state uses them",
        NoAxisWordsInPlane = 32: "Invalid gcode ID:32: G2 and G3 arcs require at least one in-plane axis word",
        InvalidTarget = 33: "Invalid gcode ID:33: motion command target is invalid",
        ArcRadius = 34: "Invalid gcode ID:34: arc radius value is invalid",
        NoOffsetsInPlane = 35: "Invalid gcode ID:35: G2 and G3 arcs require at least one in-plane offset word",
        UnusedWords = 36: "Invalid gcode ID:36: unused value words found in block",
        G43DynamicAxis = 37: "Invalid gcode ID:37: G43.1 dynamic tool length offset is not assigned to the configured tool length axis",
        ToolNumberTooLarge = 38: "Invalid gcode ID:38: tool number greater than max supported value",
    }
}

codes! {
    /// `ALARM:N` push messages: motion stopped, position possibly lost; GRBL locks out G-code.
    GrblAlarm {
        HardLimit = 1: "Hard limit triggered: machine position is likely lost due to sudden halt; re-homing is highly recommended",
        SoftLimit = 2: "Soft limit alarm: G-code motion target exceeds machine travel; machine position retained, alarm may be safely unlocked",
        AbortCycle = 3: "Reset while in motion: machine position is likely lost due to sudden halt; re-homing is highly recommended",
        ProbeFailInitial = 4: "Probe fail: the probe is not in the expected initial state before starting the probe cycle",
        ProbeFailContact = 5: "Probe fail: the probe did not contact the workpiece within the programmed travel",
        HomingFailReset = 6: "Homing fail: reset during the active homing cycle",
        HomingFailDoor = 7: "Homing fail: safety door was opened during the active homing cycle",
        HomingFailPulloff = 8: "Homing fail: cycle failed to clear the limit switch when pulling off",
        HomingFailApproach = 9: "Homing fail: could not find the limit switch within the search distance",
        HomingFailDualApproach = 10: "Homing fail: on dual-axis machines, could not find the second limit switch",
    }
}

impl GrblAlarm {
    /// After these GRBL waits for a soft reset before it accepts anything else.
    pub fn needs_reset(self) -> bool {
        matches!(self, GrblAlarm::HardLimit | GrblAlarm::SoftLimit)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_round_trip_and_carry_grbl_text() {
        for c in (1..=38).filter(|c| !(18..=19).contains(c)) {
            let e = GrblErrorCode::from_code(c);
            assert!(!matches!(e, GrblErrorCode::Unknown(_)), "error {c}");
            assert_eq!(e.code(), c);
        }
        for c in 1..=10 {
            assert_eq!(GrblAlarm::from_code(c).code(), c);
        }
        assert_eq!(
            GrblErrorCode::from_code(22),
            GrblErrorCode::UndefinedFeedRate
        );
        assert!(GrblAlarm::from_code(1).text().starts_with("Hard limit"));
        assert_eq!(GrblAlarm::from_code(77), GrblAlarm::Unknown(77));
        assert!(GrblAlarm::HardLimit.needs_reset() && !GrblAlarm::AbortCycle.needs_reset());
    }
}
