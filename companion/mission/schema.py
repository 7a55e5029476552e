"""The mission XML Schema, embedded so the installed package validates without the repository.

`MISSION_XSD` is byte-for-byte the content of `missions/mission.xsd` (a unit test keeps them equal).
"""

from __future__ import annotations

__all__ = ["MISSION_XSD"]

MISSION_XSD = r"""<?xml version="1.0" encoding="UTF-8"?>
<!--
  Inspection mission schema (companion, issue 6).  Reference: docs/missions.md.
  Units in the file: metres, seconds, metres per second, DEGREES for yaw angles.
  Numbers are plain decimals (xs:decimal: no exponent, no NaN/INF).
  Structural and type checks live here; range checks against the vehicle limits
  (speed, ceiling, geofence, timeouts) are done by companion.mission after this schema.
-->
<xs:schema xmlns:xs="http://www.w3.org/2001/XMLSchema" elementFormDefault="unqualified">

  <xs:simpleType name="number">
    <xs:restriction base="xs:decimal"/>
  </xs:simpleType>

  <xs:simpleType name="name">
    <xs:restriction base="xs:token">
      <xs:minLength value="1"/>
      <xs:maxLength value="64"/>
      <xs:pattern value="[A-Za-z0-9_.\-]+"/>
    </xs:restriction>
  </xs:simpleType>

  <xs:simpleType name="frame">
    <xs:restriction base="xs:token">
      <xs:enumeration value="ned"/>
      <xs:enumeration value="rack"/>
    </xs:restriction>
  </xs:simpleType>

  <xs:simpleType name="pipeIndex">
    <xs:restriction base="xs:positiveInteger">
      <xs:maxInclusive value="64"/>
    </xs:restriction>
  </xs:simpleType>

  <!-- Attributes every action accepts. -->
  <xs:attributeGroup name="common">
    <xs:attribute name="id" type="name"/>
    <xs:attribute name="timeout" type="number"/>
  </xs:attributeGroup>

  <!-- Attributes of the motion actions. -->
  <xs:attributeGroup name="motion">
    <xs:attribute name="speed" type="number"/>
    <xs:attribute name="threshold" type="number"/>
  </xs:attributeGroup>

  <xs:complexType name="takeoff">
    <xs:attribute name="height" type="number" use="required"/>
    <xs:attribute name="threshold" type="number"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="gotoxy">
    <xs:attribute name="x" type="number" use="required"/>
    <xs:attribute name="y" type="number" use="required"/>
    <xs:attribute name="yaw" type="number"/>
    <xs:attribute name="yaw-threshold" type="number"/>
    <xs:attributeGroup ref="motion"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="gotoz">
    <xs:attribute name="z" type="number"/>
    <xs:attribute name="height" type="number"/>
    <xs:attributeGroup ref="motion"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="takePhoto">
    <xs:attribute name="camera" type="name" use="required"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="hover">
    <xs:attribute name="seconds" type="number" use="required"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="servo">
    <xs:attribute name="pipe" type="pipeIndex" use="required"/>
    <xs:attribute name="height" type="number" use="required"/>
    <xs:attribute name="y" type="number" use="required"/>
    <xs:attribute name="yaw" type="number"/>
    <xs:attribute name="yaw-threshold" type="number"/>
    <xs:attributeGroup ref="motion"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="home">
    <xs:attributeGroup ref="motion"/>
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="land">
    <xs:attributeGroup ref="common"/>
  </xs:complexType>

  <xs:complexType name="pipe">
    <xs:attribute name="radius" type="number" use="required"/>
    <xs:attribute name="gap" type="number"/>
  </xs:complexType>

  <xs:complexType name="rack">
    <xs:sequence>
      <xs:element name="pipe" type="pipe" minOccurs="1" maxOccurs="64"/>
    </xs:sequence>
    <xs:attribute name="length" type="number" use="required"/>
  </xs:complexType>

  <xs:element name="mission">
    <xs:complexType>
      <xs:sequence>
        <xs:element name="rack" type="rack" minOccurs="0" maxOccurs="1"/>
        <xs:choice minOccurs="1" maxOccurs="unbounded">
          <xs:element name="takeoff" type="takeoff"/>
          <xs:element name="gotoxy" type="gotoxy"/>
          <xs:element name="gotoz" type="gotoz"/>
          <xs:element name="take-photo" type="takePhoto"/>
          <xs:element name="hover" type="hover"/>
          <xs:element name="servo" type="servo"/>
          <xs:element name="home" type="home"/>
          <xs:element name="land" type="land"/>
        </xs:choice>
      </xs:sequence>
      <xs:attribute name="version" type="xs:positiveInteger" fixed="1"/>
      <xs:attribute name="name" type="name" use="required"/>
      <xs:attribute name="frame" type="frame" use="required"/>
      <xs:attribute name="timeout" type="number"/>
      <xs:attribute name="speed" type="number"/>
      <xs:attribute name="threshold" type="number"/>
      <xs:attribute name="yaw-threshold" type="number"/>
      <xs:attribute name="settle" type="number"/>
    </xs:complexType>
  </xs:element>
</xs:schema>
"""
