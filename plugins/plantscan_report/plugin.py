"""Registers the report plugin's exporters: html-report, ply, obj, glb, csv, colmap."""

from __future__ import annotations

from plantscan_core.hookspecs import hookimpl
from plantscan_report.colmap import ColmapExporter
from plantscan_report.html_report import HtmlReportExporter
from plantscan_report.meshes import GlbExporter, ObjExporter, PlyExporter
from plantscan_report.tables import CsvExporter

EXPORTERS = (HtmlReportExporter, PlyExporter, ObjExporter, GlbExporter, CsvExporter, ColmapExporter)


@hookimpl
def plantscan_register_stages(registry) -> None:
    for cls in EXPORTERS:
        registry.add(cls)
