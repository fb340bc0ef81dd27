"""Measuring, recording and exporting trained policies: the paper's evaluation protocols
(`conditions`, `protocols`, `runner`), episode recordings (`recording`), run reports (`report`)."""
